import json
from types import SimpleNamespace

import numpy as np
import pytest

from evseg_torch.errors import ShapeError
from evseg_torch.evaluation.evimo import (
    EMPTY_GT,
    EVALUATED,
    TOO_FEW_EVENTS,
    FrameResult,
    background_cluster,
    evaluate_evimo,
    event_wise_iou,
    predicted_mask,
    summarize_evimo,
)
from evseg_torch.events import EVENT_DTYPE
from evseg_torch.io import load_evimo, save_evimo
from evseg_torch.pipeline import CascadedSegmenter
from evseg_torch.synthetic import make_scene

SIZE = (90, 120)
MASK_TIMES = np.array([0.015, 0.03, 0.045])


def _events(xy, t_us, p=1):
    events = np.zeros(len(xy), dtype=EVENT_DTYPE)
    events["t"], events["x"], events["y"], events["p"] = t_us, xy[:, 0], xy[:, 1], p
    return events


@pytest.fixture(scope="module")
def scene():
    # Seed 4: the background makes most of the events, as in EV-IMO, so the background rule holds.
    return make_scene(SIZE, duration=0.06, n_objects=1, n_events=40_000, rng=4)


@pytest.fixture(scope="module")
def sequence(scene, tmp_path_factory):
    masks = np.stack([scene.masks_at(t)[0].astype(np.uint8) for t in MASK_TIMES])
    path = save_evimo(tmp_path_factory.mktemp("evimo") / "seq.npz", scene.events, masks, MASK_TIMES)
    return load_evimo(path, trusted=True)


class _PerfectSegmenter:
    """Ground-truth labels (noise in the background) and every event warped by its true motion."""

    def __init__(self, scene):
        self.scene = scene
        self.xy = np.column_stack([scene.events["x"], scene.events["y"]]).astype(np.float64)

    def __call__(self, window, t_ref):
        first = np.searchsorted(self.scene.events["t"], window["t"][0], side="left")
        index = first + np.arange(len(window))
        labels = np.clip(self.scene.labels[index], 0, None)
        dt = window["t"] * 1e-6 - t_ref
        warped = np.empty((len(window), 2))
        for k, motion in enumerate(self.scene.motions):
            own = labels == k
            warped[own] = motion.model.warp(self.xy[index][own], dt[own], motion.params)
        return SimpleNamespace(labels=labels, warped_xy=warped)


def _all_background(window, t_ref):
    xy = np.column_stack([window["x"], window["y"]]).astype(np.float64)
    return SimpleNamespace(labels=np.zeros(len(window), dtype=np.int64), warped_xy=xy)


class TestProtocol:
    def test_perfect_segmenter_scores_near_one(self, scene, sequence):
        results = evaluate_evimo(_PerfectSegmenter(scene), sequence, window_ms=10, min_events=100)
        assert [r.status for r in results] == [EVALUATED] * 3
        for result in results:
            assert result.convex_hull_iou > 0.9
            # Below 1 only because the object moves during the window; the raw pixels trail it.
            assert result.event_wise_iou > 0.8
        summary = summarize_evimo(results)
        assert summary["convex_hull_iou"] > 0.9 and summary["event_wise_iou"] > 0.8
        assert summary["sr_at_0_5"] == 1.0 and summary["miou"] > 0.9 and summary["event_iou"] > 0.8

    def test_all_background_scores_zero(self, sequence):
        results = evaluate_evimo(_all_background, sequence, window_ms=10, min_events=100)
        assert all(r.evaluated and r.predicted_pixels == 0 for r in results)
        assert all(r.convex_hull_iou == 0.0 and r.event_wise_iou == 0.0 for r in results)
        assert all(r.piou == r.event_iou == 0.0 and 0.0 < r.miou < 0.5 for r in results)
        summary = summarize_evimo(results)
        assert summary["sr_at_0_5"] == 0.0 and summary["event_iou"] == 0.0

    def test_hand_made_exact(self, tmp_path):
        # A static 20 x 10 box: three events on every pixel of its outline, many more on the background.
        height, width = 40, 50
        mask = np.zeros((1, height, width), dtype=np.uint8)
        mask[0, 10:20, 15:35] = 3
        box = np.zeros((height, width), dtype=bool)
        box[10:20, 15:35] = True
        outline = box.copy()
        outline[11:19, 16:34] = False
        rows, cols = np.nonzero(outline)
        object_xy = np.repeat(np.column_stack([cols, rows]), 3, axis=0)
        rng = np.random.default_rng(0)
        background_rows, background_cols = np.nonzero(~box)
        pick = rng.integers(0, len(background_rows), 4 * len(object_xy))
        background_xy = np.column_stack([background_cols[pick], background_rows[pick]])
        xy = np.concatenate([object_xy, background_xy])
        order = rng.permutation(len(xy))
        events = _events(xy[order], np.arange(len(xy)) * 10)
        is_object = np.arange(len(xy))[order] < len(object_xy)
        t_mid = events["t"][len(events) // 2] * 1e-6
        path = save_evimo(tmp_path / "box.npz", events, mask, np.array([t_mid]))
        sequence = load_evimo(path, trusted=True)

        def oracle(window, t_ref):
            return SimpleNamespace(
                labels=np.where(is_object, 1, 0), warped_xy=np.column_stack([window["x"], window["y"]]) * 1.0
            )

        span_ms = 2e-3 * (events["t"][-1] - events["t"][0]) + 1
        (result,) = evaluate_evimo(oracle, sequence, window_ms=span_ms, min_events=1)
        assert result.n_events == len(events)
        assert result.gt_pixels == result.predicted_pixels == 200
        assert result.convex_hull_iou == 1.0
        assert result.event_wise_iou == 1.0
        assert result.miou == result.piou == result.event_iou == 1.0

    def test_skipped_frames(self, scene, tmp_path):
        masks = np.stack([scene.masks_at(0.03)[0], np.zeros(SIZE, bool), scene.masks_at(0.03)[0]])
        times = np.array([0.03, 0.03, 5.0])  # no object in the second mask, no events near the third
        sequence = load_evimo(save_evimo(tmp_path / "s.npz", scene.events, masks, times), trusted=True)
        results = evaluate_evimo(_PerfectSegmenter(scene), sequence, window_ms=10, min_events=100)
        assert [r.status for r in results] == [EVALUATED, EMPTY_GT, TOO_FEW_EVENTS]
        assert results[2].n_events == 0 and np.isnan(results[1].convex_hull_iou)
        summary = summarize_evimo(results)
        counts = (summary["frames"], summary["evaluated"], summary[EMPTY_GT], summary[TOO_FEW_EVENTS])
        assert counts == (3, 1, 1, 1)
        assert summary["convex_hull_iou"] == results[0].convex_hull_iou
        assert "convex hull" in summary["convex_hull_iou_definition"]
        assert "event-wise" in summary["event_wise_iou_definition"]
        json.dumps(summary)

    def test_real_segmenter_end_to_end(self, tmp_path):
        # Level one needs about 20 ms of a DAVIS240-sized scene to track the object.
        size, times = (180, 240), np.array([0.02, 0.04])
        scene = make_scene(size, duration=0.06, n_objects=1, rng=4)
        masks = np.stack([scene.masks_at(t)[0].astype(np.uint8) for t in times])
        sequence = load_evimo(save_evimo(tmp_path / "s.npz", scene.events, masks, times), trusted=True)
        results = evaluate_evimo(CascadedSegmenter(size), sequence, window_ms=20, min_events=100)
        assert len(results) == len(times)
        for result, t in zip(results, times, strict=True):
            assert isinstance(result, FrameResult) and result.t_s == t and result.evaluated
            assert result.n_clusters >= 1 and result.n_events > 1000
            assert result.convex_hull_iou > 0.5 and result.event_wise_iou > 0.5  # >= 0.66 measured
        summary = summarize_evimo(results)
        assert summary["evaluated"] == 2
        assert summary["convex_hull_iou"] > 0.3 and summary["event_wise_iou"] > 0.3

    def test_no_evaluated_frames(self):
        summary = summarize_evimo([FrameResult(0.0, EMPTY_GT, 10, 0, 0, 0, np.nan, np.nan)])
        assert summary["evaluated"] == 0 and np.isnan(summary["convex_hull_iou"])
        assert summarize_evimo([])["frames"] == 0


class TestPredictedMask:
    def test_noise_and_background_dropped(self):
        square = np.array([[10, 10], [20, 10], [20, 20], [10, 20]] * 3, dtype=np.float64)
        noise = np.array([[40.0, 5.0], [40.0, 5.0]])  # two events on one pixel: noise, no hull
        background = np.tile([[2.0, 2.0], [3.0, 3.0]], (20, 1))
        xy = np.concatenate([square, noise, background])
        labels = np.concatenate([np.ones(12), 2 * np.ones(2), np.zeros(40)]).astype(np.int64)
        mask = predicted_mask(xy, labels, (30, 50))
        expected = np.zeros((30, 50), dtype=bool)
        expected[10:21, 10:21] = True
        np.testing.assert_array_equal(mask, expected)

    def test_union_of_clusters_outside_and_nan_dropped(self):
        a = np.tile([[1.0, 1.0], [3.0, 1.0], [1.0, 3.0]], (3, 1))
        b = np.tile([[10.0, 10.0], [12.0, 10.0]], (3, 1))
        away = np.array([[-5.0, 1.0], [np.nan, 2.0], [100.0, 3.0]] * 3)
        xy = np.concatenate([a, b, away, np.zeros((30, 2))])
        labels = np.concatenate([np.full(9, 1), np.full(6, 2), np.full(9, 1), np.zeros(30)]).astype(np.int64)
        mask = predicted_mask(xy, labels, (20, 20))
        assert mask[1:4, 1].all() and mask[1, 1:4].all() and not mask[3, 3]
        assert mask[10, 10:13].all() and not mask[11, 10]
        assert np.count_nonzero(mask) == 6 + 3

    def test_unassigned_and_empty(self):
        assert not predicted_mask(np.zeros((5, 2)), -np.ones(5, dtype=np.int64), (4, 4)).any()
        assert not predicted_mask(np.zeros((0, 2)), np.zeros(0, dtype=np.int64), (4, 4)).any()
        with pytest.raises(ShapeError, match="warped_xy"):
            predicted_mask(np.zeros((5, 3)), np.zeros(5, dtype=np.int64), (4, 4))

    def test_background_cluster(self):
        assert background_cluster(np.array([2, 2, 1, -1, -1, -1])) == 2
        assert background_cluster(np.array([1, 0])) == 0
        assert background_cluster(np.array([-1, -1])) == -1


class TestEventWiseIou:
    def test_counts_pixels_not_events(self):
        gt = np.zeros((4, 4), dtype=bool)
        gt[0, :2] = True
        events = _events(np.array([[0, 0], [0, 0], [1, 0], [3, 3], [2, 2]]), np.arange(5))
        # Predicted pixels {(0,0), (3,3)}; GT-masked event pixels {(0,0), (1,0)}: 1 shared of 3.
        iou = event_wise_iou(events, np.array([True, False, False, True, False]), gt)
        assert iou == pytest.approx(1 / 3)

    def test_undefined_when_both_empty(self):
        events = _events(np.array([[3, 3]]), np.zeros(1))
        assert np.isnan(event_wise_iou(events, np.array([False]), np.zeros((4, 4), dtype=bool)))
        with pytest.raises(ShapeError, match="is_imo"):
            event_wise_iou(events, np.array([False, True]), np.zeros((4, 4), dtype=bool))

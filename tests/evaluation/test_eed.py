from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from evseg_torch.config import SegmenterConfig, replace_config
from evseg_torch.errors import ConfigError, ReaderError
from evseg_torch.evaluation import eed
from evseg_torch.evaluation.eed import (
    BOX_OUTCOMES,
    EED_SENSOR_SIZE,
    BoxResult,
    EedSequence,
    box_outcomes,
    cluster_boxes,
    detection_rate,
    evaluate_boxes,
    evaluate_sequence,
    evaluate_stream_boxes,
    level_one_support,
    load_eed_sequence,
    separate_in_stream,
)
from evseg_torch.events import EVENT_DTYPE
from evseg_torch.level_one.features import Correspondences
from evseg_torch.motion import Translation
from evseg_torch.pipeline import Segmentation


def _segmentation(warped_xy, labels, sensor_size=(30, 40), tracks=((), ()), track_labels=()):
    labels = np.asarray(labels, dtype=np.int64)
    n_clusters = int(labels.max()) + 1 if len(labels) else 0
    src, dst = (np.asarray(points, dtype=np.float64).reshape(-1, 2) for points in tracks)
    return SimpleNamespace(
        labels=labels,
        warped_xy=np.asarray(warped_xy, dtype=np.float64),
        n_clusters=n_clusters,
        sensor_size=sensor_size,
        feature_tracks=SimpleNamespace(src=src, dst=dst),
        feature_labels=np.asarray(track_labels, dtype=np.int64),
    )


def _events(n, t0_us=0, step_us=10, size=(30, 40), seed=0):
    rng = np.random.default_rng(seed)
    events = np.zeros(n, dtype=EVENT_DTYPE)
    events["t"] = t0_us + step_us * np.arange(n)
    events["x"], events["y"] = rng.integers(0, size[1], n), rng.integers(0, size[0], n)
    events["p"] = 1
    return events


def _result(iou, evaluable=True, over_gt=0.0, over_predicted=0.0, predicted=(0.0, 0.0, 1.0, 1.0)):
    gt = np.array([0.0, 0.0, 1.0, 1.0])
    return BoxResult(0.0, gt, evaluable, 10, np.array(predicted), iou, over_gt, 2, over_predicted)


class TestClusterBoxes:
    def test_dense_pixels_of_non_background_clusters(self):
        corners = np.array([[5.0, 6.0], [9.0, 6.0], [5.0, 8.0], [9.2, 7.6]])  # rounds onto 4 pixels
        object_xy = np.repeat(corners, 3, axis=0)
        noise = np.array([[30.0, 20.0], [30.0, 20.0]])  # 2 events on a pixel: not more than min_count
        background = np.repeat([[1.0, 1.0]], 20, axis=0)
        xy = np.concatenate([object_xy, noise, background])
        labels = np.concatenate([np.full(12, 2), np.full(2, 2), np.full(20, 0)])
        boxes = cluster_boxes(_segmentation(xy, labels))
        assert list(boxes) == [2]
        np.testing.assert_array_equal(boxes[2], [5.0, 6.0, 4.0, 2.0])

    def test_background_is_largest_cluster_whatever_its_label(self):
        xy = np.concatenate([np.repeat([[3.0, 4.0]], 10, axis=0), np.repeat([[20.0, 10.0]], 4, axis=0)])
        labels = np.array([1] * 10 + [0] * 4)
        boxes = cluster_boxes(_segmentation(xy, labels))
        assert list(boxes) == [0]
        np.testing.assert_array_equal(boxes[0], [20.0, 10.0, 0.0, 0.0])

    def test_outside_and_sparse_clusters_have_no_box(self):
        xy = np.concatenate([np.repeat([[-3.0, 4.0], [45.0, 2.0]], 5, axis=0), np.zeros((20, 2))])
        labels = np.array([1] * 10 + [0] * 20)
        assert cluster_boxes(_segmentation(xy, labels)) == {}
        assert cluster_boxes(_segmentation(np.zeros((0, 2)), [])) == {}

    def test_min_count(self):
        xy = np.concatenate([np.repeat([[3.0, 4.0]], 2, axis=0), np.zeros((5, 2))])
        labels = np.array([1, 1, 0, 0, 0, 0, 0])
        assert cluster_boxes(_segmentation(xy, labels)) == {}
        assert list(cluster_boxes(_segmentation(xy, labels), min_count=1)) == [1]


class TestDetectionRate:
    def test_counts_only_evaluable_boxes(self):
        results = [
            _result(0.9, over_gt=0.95, over_predicted=0.95),
            _result(0.5, over_gt=0.8, over_predicted=0.6, predicted=(0.0, 0.0, 3.0, 3.0)),  # 9x the GT
            _result(0.2, over_predicted=1.0, predicted=(0.0, 0.0, 0.5, 1.0)),  # half the GT, inside
            _result(1.0, False, over_predicted=1.0),
        ]
        assert [r.detected for r in results] == [True, False, False, False]
        assert [r.detected_nested for r in results] == [True, False, True, False]
        rate = detection_rate(results)
        assert rate["boxes"] == 4 and rate["evaluable"] == 3 and rate["detected"] == 1
        assert rate["detection_rate"] == pytest.approx(100 / 3)
        assert rate["detection_rate_overlap"] == pytest.approx(200 / 3)
        assert rate["detection_rate_over_predicted"] == pytest.approx(100.0)
        assert rate["detection_rate_nested"] == pytest.approx(200 / 3)
        assert rate["mean_iou"] == pytest.approx((0.9 + 0.5 + 0.2) / 3)

    def test_nothing_evaluable(self):
        rate = detection_rate([_result(1.0, False)])
        assert rate["evaluable"] == 0 and np.isnan(rate["detection_rate"])


class TestEvaluateBoxes:
    def test_centred_window_and_matching(self):
        events = _events(2000)  # 10 us apart: 0 .. 19.99 ms
        seen = []

        def stub(window, t_ref):
            seen.append((window["t"][0], window["t"][-1], t_ref))
            xy = np.concatenate(
                [np.repeat([[10.0, 10.0], [20.0, 15.0]], 3, axis=0), np.zeros((len(window) - 6, 2))]
            )
            labels = np.r_[np.ones(6, dtype=np.int64), np.zeros(len(window) - 6, dtype=np.int64)]
            return _segmentation(xy, labels)

        gt = np.array([[10.0, 10.0, 10.0, 5.0], [0.0, 0.0, 5.0, 5.0]])
        observed = []
        results = evaluate_boxes(
            stub,
            events,
            np.array([0.01, 0.0195]),
            gt,
            window_ms=4,
            min_events=300,
            on_window=lambda result, segmentation: observed.append((result, segmentation.n_clusters)),
        )
        assert seen == [(8000, 11990, 0.01)]
        assert len(observed) == 1 and observed[0][0] is results[0] and observed[0][1] == 2  # evaluable only
        first, second = results
        assert first.evaluable and first.n_events == 400 and first.iou == 1.0 and first.detected
        assert first.intersection_over_gt == 1.0 and first.intersection_over_predicted == 1.0
        assert first.n_clusters == 2
        np.testing.assert_array_equal(first.predicted_box, gt[0])
        assert first.detected_nested
        assert not second.evaluable and second.n_events == 250 and not second.detected
        assert not second.detected_nested

    def test_overlap_readings_of_a_box_inside_the_gt_box(self):
        def small_object(window, t_ref):
            xy = np.concatenate(
                [np.repeat([[12.0, 11.0], [16.0, 15.0]], 3, axis=0), np.zeros((len(window) - 6, 2))]
            )
            return _segmentation(xy, np.r_[np.ones(6), np.zeros(len(window) - 6)])

        gt = np.array([[10.0, 10.0, 10.0, 10.0]])  # 100 px^2 around the object's 4 x 4 box
        (result,) = evaluate_boxes(
            small_object, _events(100), np.array([0.0005]), gt, window_ms=1, min_events=10
        )
        np.testing.assert_array_equal(result.predicted_box, [12.0, 11.0, 4.0, 4.0])
        assert result.iou == pytest.approx(0.16) and result.intersection_over_gt == pytest.approx(0.16)
        assert result.intersection_over_predicted == 1.0 and not result.detected
        assert not result.detected_nested  # the GT box is 6.25 times the object's

    def test_nested_reading_of_a_box_inside_a_blurred_gt_box(self):
        def object_6x6(window, t_ref):
            xy = np.concatenate(
                [np.repeat([[12.0, 11.0], [18.0, 17.0]], 3, axis=0), np.zeros((len(window) - 6, 2))]
            )
            return _segmentation(xy, np.r_[np.ones(6), np.zeros(len(window) - 6)])

        gt = np.array([[10.0, 10.0, 10.0, 10.0]])
        (result,) = evaluate_boxes(
            object_6x6, _events(100), np.array([0.0005]), gt, window_ms=1, min_events=10
        )
        assert result.iou == pytest.approx(0.36) and not result.detected
        assert result.detected_nested

    def test_window_start_reference(self):
        events = _events(2000)
        seen = []

        def stub(window, t_ref):
            seen.append(t_ref)
            return _segmentation(np.zeros((len(window), 2)), np.zeros(len(window)))

        gt = np.array([[0.0, 0.0, 5.0, 5.0]])
        evaluate_boxes(
            stub, events, np.array([0.01]), gt, window_ms=4, min_events=10, reference="window_start"
        )
        assert seen == [0.008]  # the first event of the window [8, 12) ms
        with pytest.raises(ConfigError, match="reference"):
            evaluate_boxes(stub, events, np.array([0.01]), gt, window_ms=4, reference="centre")

    def test_no_candidate_box(self):
        def background_only(window, t_ref):
            return _segmentation(np.zeros((len(window), 2)), np.zeros(len(window)))

        (result,) = evaluate_boxes(
            background_only,
            _events(100),
            np.array([0.0005]),
            np.array([[1.0, 1.0, 2.0, 2.0]]),
            window_ms=1,
            min_events=10,
        )
        assert result.evaluable and result.iou == 0.0 and result.intersection_over_gt == 0.0
        assert np.isnan(result.predicted_box).all()


class TestWhyBoxesAreMissed:
    # Background (label 0) everywhere; two objects' events compensated into boxes A and B.
    A, B, C = [10.0, 10.0, 4.0, 4.0], [20.0, 10.0, 4.0, 4.0], [30.0, 20.0, 4.0, 4.0]

    def _window(self, object_labels):
        """40 background events at (2, 2), 5 events in A and 5 in B labelled ``object_labels``."""
        xy = [[2.0, 2.0]] * 40 + [[12.0, 12.0]] * 5 + [[22.0, 12.0]] * 5
        labels = [0] * 40 + [object_labels[0]] * 5 + [object_labels[1]] * 5
        return _segmentation(xy, labels)

    def test_each_reason(self):
        boxes = np.array([self.A, self.B])
        assert box_outcomes(self._window((1, 2)), boxes, [True, False]) == ["detected", "stretched"]
        assert box_outcomes(self._window((1, 1)), boxes, [False, False]) == ["merged", "merged"]
        assert box_outcomes(self._window((0, 1)), boxes, [False, False]) == ["background", "stretched"]
        no_events = np.array([self.C])
        assert box_outcomes(self._window((1, 2)), no_events, [False]) == ["unassigned"]
        assert set(BOX_OUTCOMES) == {"detected", "background", "merged", "stretched", "unassigned"}

    def test_level_one_support(self):
        # Three tracks whose midpoints lie in A (cluster 0), one in B (cluster 1, which has two more
        # elsewhere), one unclustered in B.
        src = [[11.0, 11.0], [12.0, 12.0], [13.0, 11.0], [21.0, 11.0], [5.0, 5.0], [6.0, 6.0], [22.0, 12.0]]
        dst = [[13.0, 13.0], [12.0, 12.0], [13.0, 13.0], [21.0, 13.0], [5.0, 5.0], [6.0, 6.0], [22.0, 12.0]]
        window = _segmentation(np.zeros((1, 2)), [0], tracks=(src, dst), track_labels=[0, 0, 0, 1, 1, 1, -1])
        tracks, own = level_one_support(window, np.array([self.A, self.B, self.C]))
        assert tracks.tolist() == [3, 2, 0]
        assert own.tolist() == [True, False, False]  # B holds one of cluster 1's three tracks

    def test_boxes_of_one_time_share_one_segmentation(self):
        calls = []

        def two_objects(window, t_ref):
            calls.append(t_ref)
            xy = np.concatenate(
                [[[12.0, 12.0]] * 5 + [[22.0, 12.0]] * 5, np.full((len(window) - 10, 2), 2.0)]
            )
            return _segmentation(xy, np.r_[np.ones(10), np.zeros(len(window) - 10)])

        boxes = np.array([self.A, self.B, self.A])
        results = evaluate_boxes(
            two_objects, _events(2000), np.array([0.005, 0.005, 0.015]), boxes, window_ms=4, min_events=10
        )
        assert calls == [0.005, 0.015]
        assert [r.outcome for r in results] == ["merged", "merged", "stretched"]
        rates = detection_rate(results)
        assert (rates["missed_merged"], rates["missed_stretched"], rates["missed_background"]) == (2, 1, 0)
        assert rates["boxes_with_tracks"] == rates["boxes_with_own_model"] == 0


def test_evaluate_sequence_windows_from_the_config(monkeypatch):
    built, seen = [], []

    class Stub:
        def __init__(self, sensor_size, config):
            built.append((sensor_size, config))

        def to(self, device):
            return self

        def __call__(self, window, t_ref):
            seen.append((len(window), t_ref))
            return _segmentation(np.zeros((len(window), 2)), np.zeros(len(window)))

    monkeypatch.setattr(eed, "CascadedSegmenter", Stub)
    sequence = EedSequence("s", _events(2000), np.array([0.01, 0.0195]), np.ones((2, 4)), (30, 40))
    config = replace_config(SegmenterConfig(), window_ms=4.0, min_events=300)
    results = evaluate_sequence(sequence, config)
    assert built == [((30, 40), config)]
    # 4 ms windows: 400 events around 10 ms, 250 before the end at 19.99 ms (fewer than 300).
    assert seen == [(400, 0.01)] and [r.evaluable for r in results] == [True, False]
    evaluate_sequence(sequence, config, window_ms=6.0, reference="window_start")
    assert seen[1:] == [(600, pytest.approx(0.007)), (350, pytest.approx(0.0165))]


class TestLoadSequence:
    def test_absolute_and_relative(self, tmp_path):
        absolute = tmp_path / "eed_occlusions"
        absolute.mkdir()
        (absolute / "events.txt").write_text("100.000001 3 4 1\n100.000002 5 6 0\n")
        (absolute / "boundingbox.txt").write_text("100.0000015, x= 1, y= 2, w= 3, h= 4\n")
        sequence = load_eed_sequence(absolute)
        assert sequence.name == "occlusions" and sequence.sensor_size == EED_SENSOR_SIZE
        assert sequence.events["t"].tolist() == [100_000_001, 100_000_002]
        np.testing.assert_array_equal(sequence.boxes, [[1, 2, 3, 4]])

        relative = tmp_path / "eed_what_is_background"
        relative.mkdir()
        (relative / "events.txt").write_text("0.000001 3 4 1\n")
        (relative / "boundingbox_rel.txt").write_text("0.0, x= 1, y= 2, w= 3, h= 4\n")
        assert load_eed_sequence(relative).box_times_s.tolist() == [0.0]

    def test_missing_events(self, tmp_path):
        (tmp_path / "boundingbox.txt").write_text("1.0, x= 1, y= 2, w= 3, h= 4\n")
        with pytest.raises(ReaderError, match="no events file"):
            load_eed_sequence(tmp_path)


class TestSeparateInStream:
    """Two objects boxed at one time are apart when each box's events near that time are their own
    non-background cluster's."""

    BOXES = np.array([[0.0, 0.0, 9.0, 9.0], [20.0, 0.0, 9.0, 9.0], [0.0, 0.0, 9.0, 9.0]])
    TIMES = np.array([0.005, 0.005, 0.025])  # the last time has one box: never in view

    @staticmethod
    def _window(t0_us, object_ids, left, right, n=80):
        events = np.zeros(n, dtype=EVENT_DTYPE)
        events["t"] = t0_us + 100 * np.arange(n)  # all within 3 ms of 5 ms from the 20th on
        events["x"] = np.where(np.arange(n) % 2, 25, 5)
        events["y"] = 5
        labels = np.where(np.arange(n) % 2, right, left)
        return SimpleNamespace(
            events=events, labels=labels, n_clusters=3, object_ids=np.asarray(object_ids, dtype=np.int64)
        )

    def test_apart_merged_and_background(self):
        apart = self._window(0, [0, 4, 7], 1, 2)
        assert separate_in_stream([apart], self.TIMES, self.BOXES) == (1, 1)
        merged = self._window(0, [0, 4, 7], 1, 1)
        assert separate_in_stream([merged], self.TIMES, self.BOXES) == (1, 0)
        background = self._window(0, [0, 4, 7], 0, 2)
        assert separate_in_stream([background], self.TIMES, self.BOXES) == (1, 0)

    def test_a_box_that_hardly_fires_is_not_in_view(self):
        window = self._window(0, [0, 4, 7], 1, 2)  # 30 events in each box within 3 ms of 5 ms
        assert separate_in_stream([window], self.TIMES, self.BOXES, min_events=30) == (1, 1)
        assert separate_in_stream([window], self.TIMES, self.BOXES, min_events=31) == (0, 0)

    def test_a_time_no_window_holds_is_not_in_view(self):
        later = self._window(30_000, [0, 4, 7], 1, 2)
        assert separate_in_stream([later], self.TIMES, self.BOXES) == (0, 0)


class TestEvaluateStreamBoxes:
    """A streamed window is scored at each box time it holds, its clusters compensated to that time."""

    SIZE = (30, 40)

    def _window(self, t0_us, velocity):
        # An object of 4 x 3 pixels moving at ``velocity`` px/s over 20 ms, 5 events per pixel at every
        # 1 ms, among static background events on the left (labels 1 and 0; translation models).
        xs, ys = np.meshgrid(np.arange(20, 24), np.arange(10, 13))
        times = t0_us + 1000 * np.arange(21)
        obj = np.zeros(12 * 21, dtype=EVENT_DTYPE)
        obj["t"] = np.repeat(times, 12)
        shift = velocity * (obj["t"] - (t0_us + 10_000)) * 1e-6
        obj["x"] = np.tile(xs.ravel(), 21) + np.rint(shift).astype(np.int64)
        obj["y"] = np.tile(ys.ravel(), 21)
        background = _events(400, t0_us, 50, size=(30, 10), seed=1)
        events = np.concatenate([obj, background])
        order = np.argsort(events["t"], kind="stable")
        labels = np.concatenate([np.ones(len(obj), dtype=np.int64), np.zeros(400, dtype=np.int64)])[order]
        empty = np.zeros((0, 2))
        return Segmentation(
            labels=labels,
            models=np.array([[0.0, 0.0], [velocity, 0.0]]),
            motion_model="translation",
            warped_xy=np.zeros((len(events), 2)),
            t_ref=t0_us * 1e-6,
            feature_tracks=Correspondences(empty, empty, np.zeros(0), 0.0, 0.0),
            feature_labels=np.zeros(0, dtype=np.int64),
            level_one_models=np.zeros((0, 2)),
            iwes=np.zeros((2, *self.SIZE)),
            soft_assignments=np.zeros((len(events), 2)),
            energy_history=(),
            timings_ms={},
            sensor_size=self.SIZE,
            events=events[order],
        )

    def test_clusters_are_compensated_to_the_box_time(self):
        motion = Translation(self.SIZE)
        stream = [self._window(0, 300.0), self._window(30_000, 300.0)]
        box = np.array([[20.0, 10.0, 3.0, 2.0]])  # the object at 10 ms into the first window
        (held,) = evaluate_stream_boxes(stream, np.array([0.010]), box, motion)
        assert held.evaluable and held.detected and held.outcome == "detected"
        # At 40 ms the second window's object is back at x 20-23 (it repeats): the box still holds it.
        (later,) = evaluate_stream_boxes(stream, np.array([0.040]), box, motion)
        assert later.detected
        # At 15 ms the object has moved 1.5 px right of the box time's position: IoU falls but stays.
        (moved,) = evaluate_stream_boxes(stream, np.array([0.015]), box, motion)
        assert moved.iou < held.iou
        # A time no window holds is not evaluable; a static model leaves the object smeared.
        (outside,) = evaluate_stream_boxes(stream, np.array([0.100]), box, motion)
        assert not outside.evaluable
        smeared = [replace(window, models=np.zeros((2, 2))) for window in stream]
        (blurred,) = evaluate_stream_boxes(smeared, np.array([0.010]), box, motion)
        assert blurred.iou < held.iou

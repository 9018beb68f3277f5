from pathlib import Path

import numpy as np
import pytest

from evseg_torch.errors import ConfigError, ReaderError, ShapeError
from evseg_torch.evaluation.labelled import load_labelled, score_events
from evseg_torch.evaluation.predictions import (
    default_method_name,
    evaluate_predictions,
    labels_from_masks,
    load_predictions,
    match_predictions,
)
from evseg_torch.events import as_events

PROBE = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "synthetic_probe"
needs_probe = pytest.mark.skipif(
    not PROBE.is_dir(), reason="../shared/data/synthetic_probe is not beside the repository"
)


def _events(t_us, x, y):
    return as_events(np.column_stack([np.asarray(t_us) * 1e-6, x, y, np.ones(len(t_us))]))


def _labelled(path, n=6):
    """A labelled file of ``n`` events on a 10 x 20 sensor: event i at ``(i, 2)``, ``t = 100 i`` µs."""
    np.savez(
        path,
        t_us=np.arange(n, dtype=np.int64) * 100,
        x=np.arange(n, dtype=np.int16),
        y=np.full(n, 2, dtype=np.int16),
        p=np.ones(n, dtype=np.int8),
        label=np.array([0, 0, 1, 1, -1, 0][:n], dtype=np.int8),
        ambiguous=np.array([False, True, False, False, False, False][:n]),
        sensor_size=np.array([10, 20], dtype=np.int32),
    )
    return path


def _masks_from_truth(events, labels, sensor_size, times_us):
    """Masks at ``times_us``: per pixel, the label of the latest event whose nearest mask it is."""
    height, width = sensor_size
    t_us = events["t"]
    after = np.minimum(np.searchsorted(times_us, t_us), len(times_us) - 1)
    before = np.maximum(after - 1, 0)
    frame = np.where(times_us[after] - t_us < t_us - times_us[before], after, before)
    key = (frame * height + events["y"].astype(np.int64)) * width + events["x"]
    order = np.lexsort((t_us, key))
    latest = order[np.r_[key[order][1:] != key[order][:-1], True]]
    masks = np.zeros((len(times_us), height, width), dtype=np.int64)
    masks.reshape(-1)[key[latest]] = labels[latest]
    return masks


class TestLabelsFromMasks:
    def test_nearest_mask_in_time(self):
        # Masks at 0, 10 and 30 ms; event pixels (0, 0) and (1, 0).
        masks = np.array([[[1, 2]], [[3, 4]], [[5, 6]]])
        t_us = [-500, 4_000, 5_000, 6_000, 19_000, 20_000, 21_000, 40_000]
        events = _events(np.array(t_us) - min(t_us), [0, 1, 0, 1, 0, 1, 0, 1], np.zeros(8))
        labels = labels_from_masks(events, masks, np.array([0.0, 10_000.0, 30_000.0]) - min(t_us))
        # Before the first mask: the first; midway (5 and 20 ms): the earlier; after the last: the last.
        assert labels.tolist() == [1, 2, 1, 4, 3, 4, 5, 6]
        assert labels.dtype == np.int64

    def test_one_mask(self):
        events = _events([0, 50, 90], [0, 1, 1], [0, 0, 1])
        masks = np.array([[[7, 8], [9, -1]]])
        assert labels_from_masks(events, masks, np.array([50.0])).tolist() == [7, 8, -1]

    @pytest.mark.parametrize(
        ("masks", "times", "message"),
        [
            (np.zeros((2, 2)), [0.0, 1.0], "integer layer ids"),
            (np.zeros((2, 1, 2)), [0.0, 1.0], "integer layer ids"),
            (np.zeros((0, 1, 2), dtype=int), [], "T >= 1"),
            (np.zeros((2, 1, 2), dtype=int), [0.0], "one per mask"),
            (np.zeros((2, 1, 2), dtype=int), [1.0, 1.0], "strictly increasing"),
            (np.zeros((2, 1, 2), dtype=int), [1.0, np.nan], "strictly increasing"),
        ],
    )
    def test_errors(self, masks, times, message):
        with pytest.raises(ShapeError, match=message):
            labels_from_masks(_events([0], [0], [0]), masks, np.array(times))


class TestLoadPredictions:
    @pytest.fixture
    def events(self):
        return _events([0, 100, 200, 300, 400, 500], np.arange(6), np.full(6, 2))

    def test_per_event_npy_and_npz(self, tmp_path, events):
        np.save(tmp_path / "a.npy", np.array([0, 0, 1, 1, -1, 2], dtype=np.int16))
        np.savez(tmp_path / "b.npz", labels=np.arange(6), cluster=np.ones(6, dtype=np.uint8))
        loaded = load_predictions(tmp_path / "a.npy", events, (10, 20))
        assert loaded.dtype == np.int64 and loaded.tolist() == [0, 0, 1, 1, -1, 2]
        assert load_predictions(tmp_path / "b.npz", events, (10, 20)).tolist() == list(range(6))
        assert load_predictions(tmp_path / "b.npz", events, (10, 20), field="cluster").tolist() == [1] * 6

    def test_masks_in_seconds_or_microseconds(self, tmp_path, events):
        masks = np.zeros((2, 10, 20), dtype=np.uint16)
        masks[0, 2, :3], masks[1, 2, 3:] = 1000, 2000
        np.savez(tmp_path / "s.npz", masks=masks, mask_times=np.array([0.0, 0.0005]))
        np.savez(tmp_path / "us.npz", masks=masks, mask_times_us=np.array([0, 500]))
        for name in ("s.npz", "us.npz"):
            # Events at 0-200 µs are nearest the first mask, 300-500 µs the second (250 would be midway).
            labels = load_predictions(tmp_path / name, events, (10, 20))
            assert labels.tolist() == [1000, 1000, 1000, 2000, 2000, 2000]

    def test_seconds_keep_the_midway_rule(self, tmp_path):
        # 14000 * 1e-6 s is 13999.999999999998 µs unrounded, which would put the event at 7000 µs nearer
        # the second mask.
        masks = np.stack([np.zeros((10, 20), dtype=int), np.ones((10, 20), dtype=int)])
        np.savez(tmp_path / "p.npz", masks=masks, mask_times=np.array([0, 14_000]) * 1e-6)
        events = _events([6_999, 7_000, 7_001], [0, 0, 0], [0, 0, 0])
        assert load_predictions(tmp_path / "p.npz", events, (10, 20)).tolist() == [0, 0, 1]

    def test_the_label_field_wins_over_masks(self, tmp_path, events):
        np.savez(tmp_path / "p.npz", labels=np.full(6, 3), masks=np.zeros((1, 10, 20), dtype=int))
        assert load_predictions(tmp_path / "p.npz", events, (10, 20)).tolist() == [3] * 6

    @pytest.mark.parametrize(
        ("fields", "error", "message"),
        [
            (
                {"labels": np.zeros(5, dtype=int)},
                ReaderError,
                r"'labels' must hold one integer label per event \(6\)",
            ),
            ({"labels": np.zeros(6)}, ReaderError, "got float64"),
            ({"labels": np.zeros((6, 1), dtype=int)}, ReaderError, "one integer label per event"),
            (
                {"label": np.zeros(6, dtype=int)},
                ReaderError,
                "no per-event label field 'labels' and no 'masks'",
            ),
            ({"masks": np.zeros((1, 10, 20), dtype=int)}, ReaderError, "found neither"),
            (
                {"masks": np.zeros((1, 10, 20), dtype=int), "mask_times": [0.0], "mask_times_us": [0]},
                ReaderError,
                "in one field",
            ),
            (
                {"masks": np.zeros((1, 20, 10), dtype=int), "mask_times": [0.0]},
                ShapeError,
                r"\(20, 10\) \(H, W\)",
            ),
            ({"masks": np.zeros((1, 10, 20)), "mask_times": [0.0]}, ShapeError, "integer layer ids"),
            ({"masks": np.zeros((2, 10, 20), dtype=int), "mask_times": [1.0, 0.5]}, ShapeError, "increasing"),
        ],
    )
    def test_errors_name_the_file(self, tmp_path, events, fields, error, message):
        path = tmp_path / "pred.npz"
        np.savez(path, **fields)
        with pytest.raises(error, match=message) as raised:
            load_predictions(path, events, (10, 20))
        assert str(raised.value).startswith(str(path))

    def test_bad_files(self, tmp_path, events):
        with pytest.raises(ReaderError, match="no such file"):
            load_predictions(tmp_path / "missing.npy", events, (10, 20))
        (tmp_path / "p.txt").write_text("0 0 1\n")
        with pytest.raises(ReaderError, match=r"must be an \.npy or \.npz file, got '\.txt'"):
            load_predictions(tmp_path / "p.txt", events, (10, 20))
        np.save(tmp_path / "p.npy", np.array([{"a": 1}] * 6, dtype=object))
        with pytest.raises(ReaderError, match=r"p\.npy: cannot read"):
            load_predictions(tmp_path / "p.npy", events, (10, 20))
        (tmp_path / "bad.npz").write_bytes(b"not a zip")
        with pytest.raises(ReaderError, match=r"bad\.npz: cannot read"):
            load_predictions(tmp_path / "bad.npz", events, (10, 20))


class TestMatchPredictions:
    def test_in_order(self):
        assert match_predictions(["a.npz", "b.npz"], ["x.npy", "y.npz"]) == [Path("x.npy"), Path("y.npz")]

    def test_by_stem_in_a_folder(self, tmp_path):
        (tmp_path / "a.npz").touch()
        (tmp_path / "b.npy").touch()
        matched = match_predictions(["data/a.npz", "other/b.npz"], [tmp_path])
        assert matched == [tmp_path / "a.npz", tmp_path / "b.npy"]
        with pytest.raises(ReaderError, match=r"holds no prediction c\.npz/\.npy for data/c\.npz"):
            match_predictions(["data/a.npz", "data/c.npz"], [tmp_path])
        (tmp_path / "a.npy").touch()
        with pytest.raises(ReaderError, match=r"holds both an \.npz and an \.npy prediction a\.npz/\.npy"):
            match_predictions(["a.npz"], [tmp_path])

    def test_counts_differ(self):
        with pytest.raises(ConfigError, match="2 predictions for 3 labelled files"):
            match_predictions(["a.npz", "b.npz", "c.npz"], ["x.npy", "y.npy"])


def test_default_method_name(tmp_path):
    (tmp_path / "evimo_net").mkdir()
    assert default_method_name([tmp_path / "evimo_net"]) == "evimo_net"
    assert default_method_name([tmp_path / "evimo_net" / "scene_200.npz"]) == "scene_200"
    assert default_method_name([tmp_path / "a" / "x.npz", tmp_path / "a" / "y.npz"]) == "a"
    assert default_method_name([tmp_path / "a" / "x.npz", tmp_path / "b" / "y.npz"]) == "predictions"


def test_evaluate_predictions_on_small_files(tmp_path):
    first, second = _labelled(tmp_path / "first.npz"), _labelled(tmp_path / "second.npz")
    (tmp_path / "net").mkdir()
    np.save(tmp_path / "net" / "first.npy", np.array([5, 5, 7, 7, 7, 5]))
    # Event 3 has no label: wrong for accuracy, outside object 1's cluster, and no cluster of its own.
    np.save(tmp_path / "net" / "second.npy", np.array([5, 5, 7, -1, 7, 5]))
    scores = evaluate_predictions([first, second], [tmp_path / "net"])
    assert [(s.name, s.method) for s in scores] == [("first", "net"), ("second", "net")]
    # Scored: events 0, 2, 3, 5 (event 1 is ignored, event 4 noise).
    assert (scores[0].accuracy, scores[0].iou, scores[0].count_error) == (1.0, 1.0, 0)
    assert (scores[1].accuracy, scores[1].iou, scores[1].count_error) == (0.75, 0.5, 0)
    assert all(np.isnan(s.time_ms) for s in scores)
    assert evaluate_predictions([first], [tmp_path / "net" / "first.npy"], method="m")[0].method == "m"


@needs_probe
class TestProbeScenes:
    def test_ground_truth_scores_perfectly(self, tmp_path):
        files = [PROBE / "scene_200.npz", PROBE / "scene_204.npz"]
        for path in files:
            np.save(tmp_path / f"{path.stem}.npy", np.load(path)["label"])
        scores = evaluate_predictions(files, [tmp_path])
        assert [s.name for s in scores] == ["scene_200", "scene_204"] and [s.n_objects for s in scores] == [
            1,
            3,
        ]
        for s in scores:
            assert (s.accuracy, s.iou, s.detection, s.count_error) == (1.0, 1.0, 1.0, 0)

    def test_object_moved_to_the_background(self, tmp_path):
        path = PROBE / "scene_205.npz"
        _, labels, ignore, _ = load_labelled(path)
        np.save(tmp_path / "pred.npy", np.where(labels == 1, 0, labels))
        (score,) = evaluate_predictions([path], [tmp_path / "pred.npy"])
        scored = labels[~ignore & (labels >= 0)]
        background, first = np.count_nonzero(scored == 0), np.count_nonzero(scored == 1)
        assert background > first  # so the merged cluster is still matched to the background
        # Object 1's scored events are wrong; object 1 is missed, object 2 is found whole; two of the
        # three layers remain.
        assert score.accuracy == pytest.approx(1 - first / len(scored))
        assert (score.iou, score.detection, score.count_error) == (0.5, 0.5, -1)

    def test_masks_rendered_from_the_ground_truth(self, tmp_path):
        path = PROBE / "scene_204.npz"
        events, labels, ignore, size = load_labelled(path)
        times_us = np.arange(0.0, 30_001.0, 2_000.0)
        masks = _masks_from_truth(events, labels, size, times_us)
        np.savez(tmp_path / "masks.npz", masks=masks, mask_times=times_us * 1e-6)
        (score,) = evaluate_predictions([path], [tmp_path / "masks.npz"])
        # An event is wrong only where a later event of another layer hit its pixel in its mask's time bin.
        assert score.accuracy > 0.99 and score.iou > 0.97
        assert (score.detection, score.count_error) == (1.0, 0)
        direct = labels_from_masks(events, masks, times_us)
        expected = score_events(direct, events, labels, ignore)
        assert (score.accuracy, score.iou) == (expected.accuracy, expected.iou)


def test_dynamic_class_metrics_read_labels_above_zero_as_dynamic(tmp_path):
    path = _labelled(tmp_path / "first.npz")
    binary, ids = tmp_path / "binary.npy", tmp_path / "ids.npy"
    np.save(binary, np.array([0, 0, 1, 1, 1, 0]))  # a binary dynamic mask's labels: exact
    np.save(ids, np.array([5, 5, 7, 7, 7, 5]))  # every label > 0: every event dynamic
    (exact,) = evaluate_predictions([path], [binary])
    assert (exact.dynamic_iou, exact.miou, exact.piou) == (1.0, 1.0, 1.0)
    (all_dynamic,) = evaluate_predictions([path], [ids])
    # Scored events 0, 2, 3, 5 (truth: background, object, object, background), each on its own pixel.
    assert (all_dynamic.dynamic_iou, all_dynamic.miou, all_dynamic.piou) == (0.5, 0.25, 0.5)
    assert all_dynamic.accuracy == exact.accuracy == 1.0  # the partition is right either way

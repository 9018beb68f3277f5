from types import SimpleNamespace

import numpy as np
import pytest

from evseg_torch.errors import EventFormatError, ReaderError, ShapeError
from evseg_torch.evaluation import labelled
from evseg_torch.evaluation.labelled import (
    LabelledScore,
    evaluate_labelled,
    load_labelled,
    percentile_box,
    score_labelling,
)


def _diagonal(x0, y0, n=51):
    """``n`` points on a diagonal from ``(x0, y0)``; for 51, their box is ``[x0 + 1, y0 + 1, 48, 48]``."""
    steps = np.arange(n)
    return np.column_stack([x0 + steps, y0 + steps]).astype(np.float64)


class TestPercentileBox:
    def test_spans_the_2nd_to_98th_percentiles(self):
        xy = np.column_stack([np.arange(51), 2 * np.arange(51)])
        np.testing.assert_allclose(percentile_box(xy), [1, 2, 48, 96])
        np.testing.assert_allclose(percentile_box(_diagonal(10, 10)), [11, 11, 48, 48])

    def test_no_points(self):
        assert np.isnan(percentile_box(np.zeros((0, 2)))).all()


class TestScoreLabelling:
    def test_hand_computed_with_noise_and_ignored_events_left_out(self):
        gt = np.array([0, 0, 0, 0, 1, 1, 1, 1, -1, 0])
        ignore = np.array([False] * 9 + [True])
        pred = np.array([0, 0, 0, 1, 1, 1, 1, 0, 1, 1])
        score = score_labelling(pred, gt, np.zeros((10, 2)), ignore=ignore, name="w", time_ms=12.5)
        # Scored: the first 8 events; clusters 0->0 and 1->1, events 3 and 7 wrong.
        assert score.accuracy == pytest.approx(6 / 8)
        # Object 1: {4,5,6,7} against cluster 1's scored events {3,4,5,6}; the noise and the ignored event
        # in cluster 1 would make it 3 / 7.
        assert score.iou == pytest.approx(3 / 5)
        assert (score.n_events, score.n_objects, score.count_error) == (10, 1, 0)
        assert (score.name, score.time_ms) == ("w", 12.5)

    def test_detection_by_percentile_boxes(self):
        background, first, second = _diagonal(0, 100), _diagonal(10, 10), _diagonal(100, 10)
        stray = np.full((5, 2), [230.0, 170.0])
        xy = np.concatenate([background, first, second, stray, stray])
        gt = np.concatenate([np.zeros(51), np.ones(51), np.full(51, 2), np.full(5, -1), np.zeros(5)])
        ignore = np.r_[np.zeros(158, dtype=bool), np.ones(5, dtype=bool)]
        # Object 1 is found whole (with noise and ignored events far away in its cluster); half of
        # object 2 (points 0-25) is found, the rest is labelled background.
        pred = np.concatenate([np.zeros(51), np.ones(51), np.full(26, 2), np.zeros(25), np.ones(10)])
        score = score_labelling(pred, gt, xy, ignore=ignore)
        # Object 2's cluster box [100.5, 10.5, 24, 24] against its box [101, 11, 48, 48]: IoU
        # 23.5^2 / (24^2 + 48^2 - 23.5^2) = 0.237, although its event IoU 26 / 51 is above 0.5.
        assert score.detection == 0.5
        assert score.iou == pytest.approx((1 + 26 / 51) / 2)
        assert score.accuracy == pytest.approx(128 / 153)
        assert (score.n_objects, score.count_error) == (2, 0)
        # Were the stray events scored (as background), they would stretch cluster 1's box.
        assert score_labelling(pred, np.r_[gt[:153], np.zeros(10)], xy).detection == 0.0

    def test_unmatched_object_is_missed(self):
        gt = np.array([0, 0, 1, 1])
        score = score_labelling(np.zeros(4), gt, np.zeros((4, 2)))
        assert (score.accuracy, score.iou, score.detection, score.count_error) == (0.5, 0.0, 0.0, -1)

    def test_count_error(self):
        gt, pred = np.array([0, 0, 1, 1]), np.array([0, -1, 1, 2])
        score = score_labelling(pred, gt, np.zeros((4, 2)))
        # Unassigned event 1 and event 3 (cluster 2 unmatched) are wrong; -1 is no cluster.
        assert score.accuracy == 0.5 and score.count_error == 1
        assert score_labelling(pred, gt, np.zeros((4, 2)), n_layers=3).count_error == 0

    def test_no_objects(self):
        score = score_labelling(np.zeros(3), np.array([0, 0, -1]), np.zeros((3, 2)))
        assert score.accuracy == 1.0 and score.n_objects == 0
        assert np.isnan(score.iou) and np.isnan(score.detection)

    @pytest.mark.parametrize(
        ("pred", "xy", "ignore", "message"),
        [
            (np.zeros(3), np.zeros((4, 2)), None, "same N"),
            (np.zeros(4), np.zeros((4, 3)), None, "same N"),
            (np.zeros(4), np.zeros((4, 2)), np.zeros(3, dtype=bool), "ignore mask"),
        ],
    )
    def test_wrong_lengths(self, pred, xy, ignore, message):
        with pytest.raises(ShapeError, match=message):
            score_labelling(pred, np.zeros(4), xy, ignore=ignore)


def _write(path, n=6, **fields):
    """A labelled file in the probe layout; ``fields`` replace or, set to None, drop members."""
    members = {
        "t_us": np.arange(n, dtype=np.int64) * 100,
        "x": np.arange(n, dtype=np.int16),
        "y": np.full(n, 2, dtype=np.int16),
        "p": np.ones(n, dtype=np.int8),
        "label": np.array([0, 0, 1, 1, -1, 0][:n], dtype=np.int8),
        "ambiguous": np.array([False, True, False, False, False, False][:n]),
        "sensor_size": np.array([10, 20], dtype=np.int32),
        **fields,
    }
    np.savez(path, **{name: value for name, value in members.items() if value is not None})
    return path


class TestLoadLabelled:
    def test_probe_layout(self, tmp_path):
        events, labels, ignore, size = load_labelled(_write(tmp_path / "a.npz"))
        assert size == (10, 20) and events["t"].tolist() == [0, 100, 200, 300, 400, 500]
        assert labels.dtype == np.int64 and labels.tolist() == [0, 0, 1, 1, -1, 0]
        assert ignore.tolist() == [False, True, False, False, False, False]

    def test_other_fields_and_sizes(self, tmp_path):
        path = _write(
            tmp_path / "a.npz",
            ambiguous=None,
            sensor_size=None,
            label=None,
            labels=np.zeros(6, dtype=np.int64),
            height=np.array(8),
            width=np.array(30),
        )
        _, labels, ignore, size = load_labelled(path, label_field="labels")
        assert ignore is None and size == (8, 30) and labels.tolist() == [0] * 6
        assert load_labelled(path, (5, 6), label_field="labels")[3] == (5, 6)
        assert load_labelled(_write(tmp_path / "b.npz"), ignore_field=None)[2] is None

    @pytest.mark.parametrize(
        ("fields", "message"),
        [
            ({"label": None}, "no per-event label field 'label'"),
            ({"label": np.zeros(5, dtype=np.int8)}, "one integer label per event"),
            ({"label": np.zeros(6)}, "one integer label per event"),
            ({"ambiguous": np.zeros(7, dtype=bool)}, "one flag per event"),
            ({"sensor_size": None}, "no sensor size"),
            ({"sensor_size": np.array([0, 20])}, "sensor_size field is invalid"),
        ],
    )
    def test_errors(self, tmp_path, fields, message):
        with pytest.raises(ReaderError, match=message):
            load_labelled(_write(tmp_path / "a.npz", **fields))

    def test_missing_and_corrupt_files(self, tmp_path):
        with pytest.raises(ReaderError, match="no such file"):
            load_labelled(tmp_path / "missing.npz")
        (tmp_path / "bad.npz").write_bytes(b"not a zip")
        with pytest.raises(ReaderError, match=r"bad\.npz: cannot read"):
            load_labelled(tmp_path / "bad.npz")
        (tmp_path / "events.txt").write_text("0.0 1 1 1\n")
        with pytest.raises(ReaderError, match=r"must be an \.npz file, got '\.txt'"):
            load_labelled(tmp_path / "events.txt")

    def test_events_outside_the_sensor(self, tmp_path):
        with pytest.raises(EventFormatError, match="outside"):
            load_labelled(_write(tmp_path / "a.npz"), (10, 4))


def test_evaluate_labelled_segments_each_file(tmp_path, monkeypatch):
    """Each file is segmented at its own sensor size and scored against its labels, ignore mask included."""
    built = []

    class FixedLabels:
        """Puts events 2-4 in cluster 1 and the others in cluster 0."""

        def __init__(self, sensor_size, config):
            built.append(sensor_size)

        def to(self, device):
            return self

        def __call__(self, events):
            labels = np.array([0, 0, 1, 1, 1, 0])
            return SimpleNamespace(labels=labels, timings_ms={"total": 7.0})

    monkeypatch.setattr(labelled, "CascadedSegmenter", FixedLabels)
    first = _write(tmp_path / "first.npz")
    second = _write(tmp_path / "second.npz", label=np.array([0, 0, 1, 2, 2, 0], dtype=np.int8))
    scores = evaluate_labelled([first, second])
    assert built == [(10, 20), (10, 20)] and all(isinstance(s, LabelledScore) for s in scores)
    assert [s.name for s in scores] == ["first", "second"] and [s.time_ms for s in scores] == [7.0, 7.0]
    # first: scored events 0, 2, 3, 5 all right (event 1 ignored, event 4 noise).
    assert (scores[0].accuracy, scores[0].iou, scores[0].count_error) == (1.0, 1.0, 0)
    # second: cluster 1 holds object 1's event 2 and object 2's events 3, 4, so it is matched to
    # object 2 (IoU 2 / 3) and object 1 is missed.
    assert scores[1].accuracy == pytest.approx(4 / 5) and scores[1].iou == pytest.approx(1 / 3)
    assert scores[1].count_error == -1 and scores[1].n_objects == 2


def test_evaluate_labelled_checks_every_file_before_segmenting(tmp_path, monkeypatch):
    """A bad file fails before any file is segmented (and before any progress output)."""
    built = []
    monkeypatch.setattr(labelled, "CascadedSegmenter", lambda sensor_size, config: built.append(sensor_size))
    with pytest.raises(ReaderError, match="no per-event label field"):
        evaluate_labelled(
            [_write(tmp_path / "good.npz"), _write(tmp_path / "bad.npz", label=None)], progress=True
        )
    assert built == []


def test_evaluate_labelled_names_the_method(tmp_path, monkeypatch):
    class AllBackground:
        def __init__(self, sensor_size, config):
            pass

        def to(self, device):
            return self

        def __call__(self, events):
            return SimpleNamespace(labels=np.zeros(len(events), dtype=int), timings_ms={"total": 1.0})

    monkeypatch.setattr(labelled, "CascadedSegmenter", AllBackground)
    path = _write(tmp_path / "a.npz")
    assert evaluate_labelled([path])[0].method == "evseg"
    assert evaluate_labelled([path], method="evseg-fast")[0].method == "evseg-fast"


class TestDynamicClass:
    def test_hand_computed(self):
        gt = np.array([0, 0, 0, 1, 1, -1])
        pred = np.array([0, 0, 1, 1, 1, 1])
        xy = np.array([[0, 0], [1, 0], [2, 0], [3, 0], [3, 0], [4, 0]], dtype=np.float64)
        score = score_labelling(pred, gt, xy, dynamic=pred > 0)
        # Noise (event 5) left out. Dynamic events: predicted {2, 3, 4}, true {3, 4}: IoU 2/3;
        # background {0, 1} vs {0, 1, 2}: 2/3. Pixels: predicted {(2,0), (3,0)}, true {(3,0)}: 1/2.
        assert score.dynamic_iou == pytest.approx(2 / 3) and score.miou == pytest.approx(2 / 3)
        assert score.piou == 0.5

    def test_background_rule_by_default(self):
        gt = np.array([0, 0, 0, 1, 1, 0])
        pred = np.array([5, 5, 5, 7, 7, -1])  # cluster 5 is the largest: the background
        xy = np.column_stack([np.arange(6), np.zeros(6)])
        score = score_labelling(pred, gt, xy)
        assert (score.dynamic_iou, score.miou, score.piou) == (1.0, 1.0, 1.0)
        with pytest.raises(ShapeError, match="one flag per event"):
            score_labelling(pred, gt, xy, dynamic=np.ones(2, dtype=bool))

    def test_summary(self):
        scores = [
            LabelledScore("a", 1, 1, 1.0, 1.0, 1.0, 0, dynamic_iou=0.4, miou=0.6, piou=0.5),
            LabelledScore("b", 1, 1, 1.0, 1.0, 1.0, 0, dynamic_iou=0.6, miou=0.8, piou=float("nan")),
        ]
        summary = labelled.summarize_dynamic(scores)
        assert summary["dynamic_iou"] == pytest.approx(0.5) and summary["miou"] == pytest.approx(0.7)
        assert summary["piou"] == 0.5 and summary["sr_at_0_5"] == 0.5

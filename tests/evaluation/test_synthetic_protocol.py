from functools import cache
from types import SimpleNamespace

import numpy as np
import pytest

from evseg_torch.errors import ConfigError
from evseg_torch.evaluation.synthetic import SceneScore, evaluate_synthetic, summarize
from evseg_torch.synthetic import make_scene
from evseg_torch.synthetic.families import family_kinds, make_family_scene

SIZE, DURATION = (48, 64), 0.01


class _Oracle:
    """Labels each event with its true layer (noise in the background), optionally merging objects."""

    def __init__(self, merge_objects=False, family=None):
        self.merge_objects = merge_objects
        self.scene = _scene if family is None else _hard_scene

    def __call__(self, events):
        seed = next(s for s in range(10) if np.array_equal(self.scene(s).events, events))
        labels = np.clip(self.scene(seed).labels, 0, None)
        if self.merge_objects:
            labels = np.minimum(labels, 1)
        n_clusters = int(labels.max()) + 1
        return SimpleNamespace(labels=labels, n_clusters=n_clusters, timings_ms={"total": 1.5})


@cache
def _scene(seed):
    return make_scene(SIZE, duration=DURATION, n_objects=1 + seed % 3, rng=seed)


@cache
def _hard_scene(seed):
    return make_family_scene("hard", seed, (90, 120), 0.02)


def test_oracle_scores_perfectly():
    scores = evaluate_synthetic(_Oracle(), [0, 1], sensor_size=SIZE, duration=DURATION)
    assert [s.seed for s in scores] == [0, 1] and [s.n_objects for s in scores] == [1, 2]
    for score in scores:
        assert isinstance(score, SceneScore)
        assert score.accuracy == 1.0 and score.iou == 1.0 and score.detection == 1.0
        assert score.count_error == 0 and score.time_ms == 1.5
        assert score.n_events == len(_scene(score.seed).events)
    summary = summarize(scores)
    assert summary["scenes"] == 2 and summary["accuracy"] == 1.0 and summary["abs_count_error"] == 0.0


def test_merged_objects_lose_one():
    (score,) = evaluate_synthetic(_Oracle(merge_objects=True), [1], sensor_size=SIZE, duration=DURATION)
    scene = _scene(1)
    labels = scene.labels[~scene.ambiguous]  # ambiguous events are left out
    assert scene.ambiguous.any()
    assert score.count_error == -1 and score.detection == 0.5
    # One object's events land in the merged cluster, which is matched to the other object.
    objects = np.bincount(labels[labels > 0])[1:]
    assert score.accuracy == pytest.approx(1 - objects.min() / np.count_nonzero(labels >= 0))
    assert score.iou == pytest.approx(objects.max() / objects.sum() / 2)
    assert summarize([score])["count_error"] == -1.0


def test_hard_family_oracle_scores_perfectly_and_names_the_kinds():
    seeds = [0, 1, 2, 3]
    scores = evaluate_synthetic(
        _Oracle(family="hard"), seeds, family="hard", sensor_size=(90, 120), duration=0.02
    )
    assert [s.kinds for s in scores] == ["+".join(family_kinds("hard", s)) for s in seeds]
    assert [s.n_events for s in scores] == [len(_hard_scene(s).events) for s in seeds]
    for score in scores:
        assert score.accuracy == score.iou == score.detection == 1.0 and score.count_error == 0
        assert score.outcomes == ("detected",) * score.n_objects


def test_hard_family_merged_objects_miss_detections():
    (score,) = evaluate_synthetic(
        _Oracle(merge_objects=True, family="hard"), [0], family="hard", sensor_size=(90, 120), duration=0.02
    )
    assert _hard_scene(0).n_objects == 3
    # The merged cluster matches one object, but its box spans all three: none is detected.
    assert score.count_error == -2 and score.detection == 0.0 and score.iou < 1 / 3
    assert score.outcomes == ("merged",) * 3


def test_unknown_family_is_a_config_error():
    with pytest.raises(ConfigError):
        evaluate_synthetic(_Oracle(), [0], family="easy", sensor_size=SIZE, duration=DURATION)


def test_summary_has_means_and_10th_percentiles():
    scores = [SceneScore(s, 1, 100, 0.5 + s / 20, s / 10, float(s >= 2), 0, 1.0) for s in range(10)]
    summary = summarize(scores)
    assert summary["accuracy"] == pytest.approx(0.725) and summary["iou"] == pytest.approx(0.45)
    assert summary["accuracy_p10"] == pytest.approx(0.545) and summary["iou_p10"] == pytest.approx(0.09)
    assert summary["detection"] == pytest.approx(0.8) and summary["detection_p10"] == 0.0


def test_summary_counts_the_misses_by_reason():
    outcomes = [("detected", "merged"), ("merged", "background"), ("split",), ()]
    scores = [SceneScore(s, 2, 100, 1.0, 1.0, 1.0, 0, 1.0, outcomes=o) for s, o in enumerate(outcomes)]
    summary = summarize(scores)
    assert (summary["missed_merged"], summary["missed_background"], summary["missed_split"]) == (2, 1, 1)
    assert summary["missed_stretched"] == 0 and "missed_detected" not in summary


def test_true_models_reach_the_segmenter():
    # The true-model ceiling (benchmarks/bench_ceiling.py) hands each scene's true motions to level two.
    given = []

    def segmenter(events, initial_models):
        given.append(initial_models)
        return SimpleNamespace(
            labels=np.zeros(len(events), dtype=int), n_clusters=1, timings_ms={"total": 1.0}
        )

    evaluate_synthetic(segmenter, [1], sensor_size=SIZE, duration=DURATION, true_models=True)
    np.testing.assert_array_equal(given[0], np.stack([m.params for m in _scene(1).motions]))

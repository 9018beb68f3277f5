from functools import cache
from types import SimpleNamespace

import numpy as np
import pytest

from evseg_torch.evaluation.synthetic import SceneScore, evaluate_synthetic, summarize
from evseg_torch.synthetic import make_scene

SIZE, DURATION = (48, 64), 0.01


class _Oracle:
    """Labels each event with its true layer (noise in the background), optionally merging objects."""

    def __init__(self, merge_objects=False):
        self.merge_objects = merge_objects

    def __call__(self, events):
        seed = next(s for s in range(10) if np.array_equal(_scene(s).events, events))
        labels = np.clip(_scene(seed).labels, 0, None)
        if self.merge_objects:
            labels = np.minimum(labels, 1)
        n_clusters = int(labels.max()) + 1
        return SimpleNamespace(labels=labels, n_clusters=n_clusters, timings_ms={"total": 1.5})


@cache
def _scene(seed):
    return make_scene(SIZE, duration=DURATION, n_objects=1 + seed % 3, rng=seed)


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
    labels = _scene(1).labels
    assert score.count_error == -1 and score.detection == 0.5
    # One object's events land in the merged cluster, which is matched to the other object.
    objects = np.bincount(labels[labels > 0])[1:]
    assert score.accuracy == pytest.approx(1 - objects.min() / np.count_nonzero(labels >= 0))
    assert score.iou == pytest.approx(objects.max() / objects.sum() / 2)
    assert summarize([score])["count_error"] == -1.0

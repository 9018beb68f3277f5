"""The synthetic benchmarks: seeded scenes with exact ground truth, the whole scene one window.

Two families of scenes:

* the default (``family=None``): seed ``s`` has ``1 + s % 3`` objects of
  :func:`~evseg_torch.synthetic.make_scene`;
* ``"hard"``: :func:`~evseg_torch.synthetic.families.make_family_scene`, the failure modes we know of
  (similar motions, rotating and scaling objects, small fast objects in sparse windows, weak textures),
  scored as the labelled probe scenes are, by :func:`~evseg_torch.evaluation.labelled.score_labelling`.

Noise events and ambiguous ones (:attr:`~evseg_torch.synthetic.SyntheticScene.ambiguous`: background
uncovered behind a moving object, whose layer is not well defined) are left out of every metric, in both
families. Reported per scene:

* ``accuracy``: event-labelling accuracy under the best one-to-one cluster matching;
* ``iou``: mean per-object event IoU (each object against its matched cluster);
* ``detection``: fraction of objects detected: whose matched cluster has event IoU > 0.5 (default family),
  or whose matched cluster's 2nd-98th percentile box has IoU > 0.5 with the object's (``hard``);
* ``count_error``: clusters found minus true layers (background included);
* ``outcomes``: per object, ``"detected"`` or why it was missed
  (:func:`~.metrics.object_outcomes`); :func:`summarize` counts the misses of each kind;
* ``time_ms``: wall time of the segmentation of the window.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from evseg_torch.evaluation.evimo import background_cluster
from evseg_torch.evaluation.metrics import OUTCOMES, labelling_accuracy, object_outcomes, per_object_iou


@dataclass(frozen=True)
class SceneScore:
    """Scores of one scene; ``kinds`` names its failure modes (``similar+spinning``) in a family;
    ``outcomes`` is each object's outcome (:func:`~.metrics.object_outcomes`)."""

    seed: int
    n_objects: int
    n_events: int
    accuracy: float
    iou: float
    detection: float
    count_error: int
    time_ms: float
    kinds: str = ""
    outcomes: tuple[str, ...] = ()


def evaluate_synthetic(
    segmenter,
    seeds,
    *,
    family=None,
    sensor_size=(180, 240),
    duration=0.03,
    progress=False,
    true_models=False,
) -> list[SceneScore]:
    """Score a segmenter on the synthetic scenes of the given seeds.

    Args:
        segmenter: a callable ``segmenter(events) -> Segmentation`` (e.g. a
            :class:`~evseg_torch.pipeline.CascadedSegmenter` built for ``sensor_size``).
        seeds: scene seeds.
        family: ``None`` for the default scenes, or a name of
            :data:`~evseg_torch.synthetic.families.FAMILIES`.
        sensor_size: ``(H, W)``.
        duration: seconds per scene.
        true_models: give the segmenter each scene's true motions as ``initial_models`` (with
            ``level_one.initial_models: replace``, level two starts from them: the true-model ceiling).

    Returns:
        One :class:`SceneScore` per seed.

    Raises:
        ConfigError: unknown family.
    """
    from tqdm.auto import tqdm

    scores = []
    for seed in tqdm(list(seeds), desc="scenes", disable=not progress):
        if family is None:
            scores.append(_score_default(segmenter, int(seed), sensor_size, duration, true_models))
        else:
            scores.append(_score_family(segmenter, family, int(seed), sensor_size, duration, true_models))
    return scores


def summarize(scores) -> dict[str, float]:
    """Means over scenes (``abs_count_error`` is the mean absolute cluster-count error), the 10th
    percentiles ``accuracy_p10``, ``iou_p10`` and ``detection_p10`` over scenes (the worst tenth), and
    ``missed_<outcome>``: how many objects were missed for each reason of
    :func:`~.metrics.object_outcomes`, over all scenes."""
    table = [asdict(s) for s in scores]
    summary = {"scenes": len(table)}
    for key in ("accuracy", "iou", "detection"):
        values = [r[key] for r in table]
        summary[key] = float(np.mean(values))
        summary[f"{key}_p10"] = float(np.percentile(values, 10))
    return {
        **summary,
        "count_error": float(np.mean([r["count_error"] for r in table])),
        "abs_count_error": float(np.mean([abs(r["count_error"]) for r in table])),
        "time_ms_median": float(np.median([r["time_ms"] for r in table])),
        **{
            f"missed_{outcome}": float(sum(r["outcomes"].count(outcome) for r in table))
            for outcome in OUTCOMES[1:]
        },
    }


def _segment(segmenter, scene, true_models: bool):
    if not true_models:
        return segmenter(scene.events)
    return segmenter(scene.events, initial_models=np.stack([motion.params for motion in scene.motions]))


def _score_default(segmenter, seed: int, sensor_size, duration, true_models: bool) -> SceneScore:
    from evseg_torch.synthetic import make_scene

    n_objects = 1 + seed % 3
    scene = make_scene(sensor_size=sensor_size, duration=duration, n_objects=n_objects, rng=seed)
    result = _segment(segmenter, scene, true_models)
    truth = np.where(scene.ambiguous, -1, scene.labels)
    ious = np.array(list(per_object_iou(result.labels, truth).values()))
    dynamic = (result.labels >= 0) & (result.labels != background_cluster(result.labels))
    return SceneScore(
        seed=seed,
        n_objects=n_objects,
        n_events=len(scene.events),
        accuracy=labelling_accuracy(result.labels, truth),
        iou=float(ious.mean()),
        detection=float(np.mean(ious > 0.5)),
        count_error=int(result.n_clusters - len(scene.motions)),
        time_ms=float(result.timings_ms["total"]),
        outcomes=object_outcomes(result.labels, truth, ious > 0.5, dynamic),
    )


def _score_family(segmenter, family: str, seed: int, sensor_size, duration, true_models: bool) -> SceneScore:
    from evseg_torch.evaluation.labelled import score_labelling
    from evseg_torch.synthetic.families import family_kinds, make_family_scene

    scene = make_family_scene(family, seed, sensor_size=sensor_size, duration=duration)
    result = _segment(segmenter, scene, true_models)
    xy = np.column_stack([scene.events["x"], scene.events["y"]])
    score = score_labelling(
        result.labels, scene.labels, xy, ignore=scene.ambiguous, n_layers=len(scene.motions)
    )
    return SceneScore(
        seed=seed,
        n_objects=scene.n_objects,
        n_events=len(scene.events),
        accuracy=score.accuracy,
        iou=score.iou,
        detection=score.detection,
        count_error=score.count_error,
        time_ms=float(result.timings_ms["total"]),
        kinds="+".join(family_kinds(family, seed)),
        outcomes=score.outcomes,
    )

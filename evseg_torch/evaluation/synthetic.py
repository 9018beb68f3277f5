"""The synthetic benchmark: seeded scenes with 1–3 moving objects and exact ground truth.

Per scene (seed ``s`` has ``1 + s % 3`` objects), the whole scene is one window. Reported:

* ``accuracy``: event-labelling accuracy under the best one-to-one cluster matching (noise excluded);
* ``iou``: mean per-object event IoU (each object against its matched cluster);
* ``detection``: fraction of objects whose matched cluster has event IoU > 0.5;
* ``count_error``: clusters found minus true layers (background included);
* ``time_ms``: wall time of the segmentation of the window.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from evseg_torch.metrics import labelling_accuracy, per_object_iou


@dataclass(frozen=True)
class SceneScore:
    seed: int
    n_objects: int
    n_events: int
    accuracy: float
    iou: float
    detection: float
    count_error: int
    time_ms: float


def evaluate_synthetic(
    segmenter, seeds, *, sensor_size=(180, 240), duration=0.03, progress=False
) -> list[SceneScore]:
    """Score a segmenter on the synthetic scenes of the given seeds.

    Args:
        segmenter: a callable ``segmenter(events) -> Segmentation`` (e.g. a
            :class:`~evseg_torch.pipeline.CascadedSegmenter` built for ``sensor_size``).
        seeds: scene seeds.

    Returns:
        One :class:`SceneScore` per seed.
    """
    from tqdm.auto import tqdm

    from evseg_torch.synthetic import make_scene

    scores = []
    for seed in tqdm(list(seeds), desc="scenes", disable=not progress):
        n_objects = 1 + seed % 3
        scene = make_scene(sensor_size=sensor_size, duration=duration, n_objects=n_objects, rng=seed)
        result = segmenter(scene.events)
        ious = np.array(list(per_object_iou(result.labels, scene.labels).values()))
        scores.append(
            SceneScore(
                seed=int(seed),
                n_objects=n_objects,
                n_events=len(scene.events),
                accuracy=labelling_accuracy(result.labels, scene.labels),
                iou=float(ious.mean()),
                detection=float(np.mean(ious > 0.5)),
                count_error=int(result.n_clusters - len(scene.motions)),
                time_ms=float(result.timings_ms["total"]),
            )
        )
    return scores


def summarize(scores: list[SceneScore]) -> dict[str, float]:
    """Means over scenes (``abs_count_error`` is the mean absolute cluster-count error)."""
    table = [asdict(s) for s in scores]
    return {
        "scenes": len(table),
        "accuracy": float(np.mean([r["accuracy"] for r in table])),
        "iou": float(np.mean([r["iou"] for r in table])),
        "detection": float(np.mean([r["detection"] for r in table])),
        "count_error": float(np.mean([r["count_error"] for r in table])),
        "abs_count_error": float(np.mean([abs(r["count_error"]) for r in table])),
        "time_ms_median": float(np.median([r["time_ms"] for r in table])),
    }

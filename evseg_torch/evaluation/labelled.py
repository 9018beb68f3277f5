"""Scoring against per-event ground-truth labels (the layout of ``shared/data/synthetic_probe``).

A labelled file holds events and, per event, its true layer (0 the background, 1..K the moving objects,
-1 noise) and optionally a boolean ignore mask (``ambiguous``: background uncovered behind a moving
object, whose events move with the object). Noise and ignored events are left out of every metric,
whatever label they get. Per window:

* ``accuracy``: best one-to-one matching of predicted clusters to true layers by event overlap; fraction
  of the scored events whose cluster is matched to their true layer;
* ``iou``: per moving object, event-set IoU with its matched cluster (0 when unmatched); mean over objects;
* ``detection``: fraction of moving objects whose matched cluster's events have a bounding box (2nd–98th
  percentile of x and y) with IoU > 0.5 against the box of the object's own events (same percentiles);
* ``count_error``: predicted clusters minus true layers (background included);
* ``outcomes``: per moving object, ``"detected"`` or why it was missed
  (:func:`~.metrics.object_outcomes`: held by the background, merged with another object, split
  over clusters, or its own cluster's box stretched);
* the dynamic-class metrics of learned maskers (:mod:`.metrics`), on the scored events:
  events are *dynamic* in truth when their layer is > 0, and predicted dynamic when off the background
  (the cascade: any cluster but the largest, the background rule of :mod:`~evseg_torch.evaluation.evimo`;
  another method's predictions: a label > 0, as in EV-IMO masks and binary dynamic masks). ``dynamic_iou`` is
  the event IoU of the dynamic class, ``miou`` the mean of the dynamic and background event IoUs, ``piou`` the
  IoU of the pixels holding predicted-dynamic events and those holding truly dynamic events (per-event ground
  truth has no dense mask, so only pixels with events count, as in pIoU); :func:`summarize_dynamic` adds
  ``sr_at_0_5``, the fraction of files whose ``dynamic_iou`` is at least 0.5.

:func:`evaluate_labelled` segments each file as one window with
:class:`~evseg_torch.pipeline.CascadedSegmenter` and scores it (``evseg evaluate labelled``);
:func:`~evseg_torch.evaluation.predictions.evaluate_predictions` scores another method's output on the
same files through the same :func:`score_events` (``evseg evaluate labelled --predictions``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evseg_torch.config import SegmenterConfig
from evseg_torch.errors import EventFormatError, ReaderError, ShapeError
from evseg_torch.evaluation.evimo import background_cluster
from evseg_torch.evaluation.metrics import (
    box_iou,
    labelling_accuracy,
    mask_iou,
    match_clusters,
    mean_iou,
    object_outcomes,
    per_object_iou,
    success_rate,
)
from evseg_torch.events import check_sensor_size
from evseg_torch.io import load_events, read_sensor_size
from evseg_torch.io.guard import existing_file, reading
from evseg_torch.io.numpy_files import WHAT_NPZ, open_npz
from evseg_torch.pipeline import CascadedSegmenter

__all__ = [
    "LabelledScore",
    "evaluate_labelled",
    "load_labelled",
    "percentile_box",
    "score_events",
    "score_labelling",
    "summarize_dynamic",
]

_NOISE = -1
# The box of a cluster or an object spans these percentiles of its events' x and y: a few stray events
# (noise labelled into the cluster, a trailing edge) do not stretch it.
_BOX_PERCENTILES = (2.0, 98.0)


@dataclass(frozen=True)
class LabelledScore:
    """Scores of one labelled window (see the module docstring for the definitions).

    ``method`` names what labelled the events: ``"evseg"`` for the cascade, else the scored predictions'
    method; ``time_ms`` is NaN when the labelling's time is not known. ``dynamic_iou``, ``miou`` and
    ``piou`` are the dynamic-class metrics (module docstring), NaN where undefined; ``outcomes`` says, per
    moving object in increasing layer order, ``"detected"`` or why it was missed.
    """

    name: str
    n_events: int
    n_objects: int
    accuracy: float
    iou: float
    detection: float
    count_error: int
    time_ms: float = float("nan")
    method: str = "evseg"
    dynamic_iou: float = float("nan")
    miou: float = float("nan")
    piou: float = float("nan")
    outcomes: tuple[str, ...] = ()


def percentile_box(xy: np.ndarray) -> np.ndarray:
    """``[x, y, w, h]`` box spanning the 2nd–98th percentiles of points :math:`(N, 2)`; NaNs if none."""
    if len(xy) == 0:
        return np.full(4, np.nan)
    low, high = np.percentile(xy, _BOX_PERCENTILES, axis=0)
    return np.array([low[0], low[1], high[0] - low[0], high[1] - low[1]])


def score_labelling(
    pred: np.ndarray,
    gt: np.ndarray,
    xy: np.ndarray,
    *,
    ignore: np.ndarray | None = None,
    n_layers: int | None = None,
    name: str = "",
    time_ms: float = float("nan"),
    method: str = "evseg",
    dynamic: np.ndarray | None = None,
) -> LabelledScore:
    """Score predicted clusters against true layers.

    Args:
        pred: predicted cluster of each event, :math:`(N,)`; negative values are unassigned.
        gt: true layer of each event, :math:`(N,)`: 0 background, 1..K objects, -1 noise.
        xy: event pixel coordinates :math:`(N, 2)` (x the column, y the row), for the detection boxes.
        ignore: events left out of every metric, bool :math:`(N,)`; ``None`` for none.
        n_layers: true layers including the background (default: the distinct labels >= 0 of ``gt``).
        name, time_ms, method: copied into the score.
        dynamic: whether each event is predicted dynamic, bool :math:`(N,)`; default: off the largest
            cluster (the background rule).

    Returns:
        :class:`LabelledScore`.

    Raises:
        ShapeError: if the arrays differ in length.
    """
    pred = np.asarray(pred).astype(np.int64)
    gt = np.asarray(gt).astype(np.int64)
    xy = np.asarray(xy, dtype=np.float64)
    if pred.shape != gt.shape or pred.ndim != 1 or xy.shape != (len(gt), 2):
        raise ShapeError(
            f"labels must be (N,) and xy (N, 2) for the same N, got {pred.shape}, {gt.shape}, {xy.shape}"
        )
    scored = gt.copy()
    if ignore is not None:
        ignore = np.asarray(ignore, dtype=bool)
        if ignore.shape != gt.shape:
            raise ShapeError(f"the ignore mask must be ({len(gt)},), got {ignore.shape}")
        scored[ignore] = _NOISE
    objects = [int(v) for v in np.unique(scored) if v > 0]
    n_layers = len(np.unique(gt[gt >= 0])) if n_layers is None else int(n_layers)
    mapping = {layer: cluster for cluster, layer in match_clusters(pred, scored, _NOISE).items()}
    ious = per_object_iou(pred, scored, objects, _NOISE)
    detected = [
        layer in mapping
        and box_iou(
            percentile_box(xy[(pred == mapping[layer]) & (scored != _NOISE)]),
            percentile_box(xy[scored == layer]),
        )
        > 0.5
        for layer in objects
    ]
    clusters = len(np.unique(pred[pred >= 0]))
    if dynamic is None:
        dynamic = (pred >= 0) & (pred != background_cluster(pred))
    dynamic = np.asarray(dynamic, dtype=bool)
    if dynamic.shape != gt.shape:
        raise ShapeError(f"dynamic must be ({len(gt)},), one flag per event, got {dynamic.shape}")
    kept = scored != _NOISE
    pred_dynamic, gt_dynamic = dynamic[kept], scored[kept] > 0
    return LabelledScore(
        name=name,
        n_events=len(gt),
        n_objects=len(objects),
        accuracy=labelling_accuracy(pred, scored, _NOISE),
        iou=float(np.mean(list(ious.values()))) if objects else float("nan"),
        detection=float(np.mean(detected)) if objects else float("nan"),
        count_error=int(clusters - n_layers),
        time_ms=float(time_ms),
        method=method,
        dynamic_iou=mask_iou(pred_dynamic, gt_dynamic),
        miou=mean_iou(pred_dynamic, gt_dynamic),
        piou=_pixel_iou(xy[kept], pred_dynamic, gt_dynamic),
        outcomes=object_outcomes(pred, scored, detected, dynamic, _NOISE),
    )


def summarize_dynamic(scores) -> dict[str, float]:
    """Means over files of ``dynamic_iou``, ``miou`` and ``piou`` (NaN files left out), and ``sr_at_0_5``.

    Returns:
        ``{"dynamic_iou", "miou", "piou", "sr_at_0_5"}``, each NaN when no file defines it.
    """

    def mean(name: str) -> float:
        values = [getattr(s, name) for s in scores if not np.isnan(getattr(s, name))]
        return float(np.mean(values)) if values else float("nan")

    return {
        "dynamic_iou": mean("dynamic_iou"),
        "miou": mean("miou"),
        "piou": mean("piou"),
        "sr_at_0_5": success_rate([s.dynamic_iou for s in scores]),
    }


def _pixel_iou(xy: np.ndarray, pred_dynamic: np.ndarray, gt_dynamic: np.ndarray) -> float:
    """IoU of the pixels holding predicted-dynamic events and those holding truly dynamic events."""
    pixels = np.unique(np.rint(xy).astype(np.int64), axis=0, return_inverse=True)[1].ravel()
    predicted, truth = np.unique(pixels[pred_dynamic]), np.unique(pixels[gt_dynamic])
    union = len(np.union1d(predicted, truth))
    return len(np.intersect1d(predicted, truth)) / union if union else float("nan")


def score_events(
    pred: np.ndarray,
    events: np.ndarray,
    labels: np.ndarray,
    ignore: np.ndarray | None,
    *,
    name: str = "",
    time_ms: float = float("nan"),
    method: str = "evseg",
    dynamic: np.ndarray | None = None,
) -> LabelledScore:
    """Score a labelling of a labelled file's events, as :func:`load_labelled` returns them.

    Args:
        pred: predicted cluster of each event, :math:`(N,)`; negative values are unassigned.
        events: canonical events :math:`(N,)`; their ``x`` and ``y`` place the detection boxes.
        labels, ignore: the file's true layers :math:`(N,)` and ignore mask :math:`(N,)` or ``None``.
        name, time_ms, method: copied into the score.
        dynamic: as in :func:`score_labelling`.

    Returns:
        :class:`LabelledScore`.
    """
    xy = np.column_stack([events["x"], events["y"]])
    return score_labelling(
        pred, labels, xy, ignore=ignore, name=name, time_ms=time_ms, method=method, dynamic=dynamic
    )


def load_labelled(
    path: str | Path,
    sensor_size: tuple[int, int] | None = None,
    *,
    label_field: str = "label",
    ignore_field: str | None = "ambiguous",
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, tuple[int, int]]:
    """Events, per-event labels and the ignore mask of a labelled ``.npz`` file.

    Args:
        path: the file; its events are read by :func:`~evseg_torch.io.load_events` (any ``.npz``
            layout it knows, e.g. ``t_us``, ``x``, ``y``, ``p`` columns).
        sensor_size: ``(H, W)``; default from the file's ``sensor_size`` field, else the size the
            file stores (``height`` and ``width``).
        label_field: the per-event integer label array.
        ignore_field: the per-event mask of events left out of the metrics; a file without it ignores
            none. ``None`` ignores none.

    Returns:
        ``(events, labels, ignore, sensor_size)``: canonical events :math:`(N,)`, int64 labels
        :math:`(N,)`, bool mask :math:`(N,)` or ``None``, and ``(H, W)``.

    Raises:
        ReaderError: the file is missing, not an ``.npz`` or unreadable, lacks the label field or a
            sensor size, or its labels or mask do not match the events one to one.
        EventFormatError: the events are invalid, e.g. outside the sensor.
    """
    path = existing_file(path)
    if path.suffix.lower() != ".npz":
        raise ReaderError(f"{path}: labelled events must be an .npz file, got {path.suffix!r}")
    wanted = {label_field, ignore_field, "sensor_size"}
    with reading(path, WHAT_NPZ), open_npz(path) as npz:
        fields = {name: npz[name] for name in npz.files if name in wanted}
        names = npz.files
    if label_field not in fields:
        raise ReaderError(f"{path}: no per-event label field {label_field!r} (fields: {', '.join(names)})")
    if sensor_size is None and "sensor_size" in fields:
        try:
            sensor_size = check_sensor_size(fields["sensor_size"])
        except EventFormatError as err:
            raise ReaderError(f"{path}: the sensor_size field is invalid: {err}") from None
    sensor_size = sensor_size or read_sensor_size(path)
    if sensor_size is None:
        raise ReaderError(f"{path}: the file stores no sensor size; give the sensor size")
    events = load_events(path, sensor_size=sensor_size)
    labels = np.asarray(fields[label_field])
    if labels.shape != (len(events),) or not np.issubdtype(labels.dtype, np.integer):
        raise ReaderError(
            f"{path}: {label_field!r} must hold one integer label per event ({len(events)}), "
            f"got {labels.dtype} {labels.shape}"
        )
    ignore = fields.get(ignore_field)
    if ignore is not None:
        if ignore.shape != (len(events),):
            raise ReaderError(
                f"{path}: {ignore_field!r} must hold one flag per event ({len(events)}), got {ignore.shape}"
            )
        ignore = ignore.astype(bool)
    return events, labels.astype(np.int64), ignore, tuple(sensor_size)


def evaluate_labelled(
    paths,
    config: SegmenterConfig | None = None,
    *,
    sensor_size: tuple[int, int] | None = None,
    label_field: str = "label",
    ignore_field: str | None = "ambiguous",
    method: str = "evseg",
    progress: bool = False,
    device: str = "cpu",
) -> list[LabelledScore]:
    """Segment each labelled file as one window and score it.

    Every file is read and checked before the first is segmented, so a bad file fails at once, before
    any progress output (labelled files are single windows, small enough to hold together).

    Args:
        paths: labelled ``.npz`` files (see :func:`load_labelled`).
        config: the pipeline's config; defaults to the built-in defaults.
        sensor_size: ``(H, W)`` of every file; default from each file.
        label_field, ignore_field: as in :func:`load_labelled`.
        method: the name of the scores' method.
        progress: show a progress bar.
        device: torch device of level two.

    Returns:
        One :class:`LabelledScore` per file, named by the file's stem, with the segmentation's time.

    Raises:
        ReaderError, EventFormatError: as in :func:`load_labelled`.
    """
    from tqdm.auto import tqdm

    cases = [
        (Path(path), *load_labelled(path, sensor_size, label_field=label_field, ignore_field=ignore_field))
        for path in paths
    ]
    scores = []
    for path, events, labels, ignore, size in tqdm(cases, desc="files", disable=not progress):
        result = CascadedSegmenter(size, config).to(device)(events)
        scores.append(
            score_events(
                result.labels,
                events,
                labels,
                ignore,
                name=path.stem,
                time_ms=result.timings_ms["total"],
                method=method,
            )
        )
    return scores

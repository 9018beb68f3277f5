"""Object ids that persist across a stream's windows, and which clusters share a motion (NumPy, SciPy).

Level two numbers a window's clusters afresh, so cluster ``k`` of one window has nothing to do with
cluster ``k`` of the next. :class:`ObjectTracker` gives every cluster an *object id* that follows it from
window to window:

* **Describing a cluster** (:func:`describe_clusters`): its event count, and the centre (median of x
  and y) and box ``[x, y, w, h]`` (2nd-98th percentile of x and y, so a few stray events do not widen
  it) of its events warped by its own model to the window's reference time ``t_ref``: a sharp,
  motion-compensated position and extent. The median holds where a cluster also took a few events
  far from its object, which moves a box's centre.
* **Background**: the cluster with the most events has id 0 when its box covers at least
  :data:`BACKGROUND_COVER` of the sensor's area; otherwise no cluster of the window has id 0. Id 0
  always means the background and is never given to an object.
* **Matching** (:func:`match_objects`): each object (id above 0) of the previous window is predicted to
  the new window's ``t_ref`` by its own model (its centre moved by ``predict``). The cost of
  continuing it with a new cluster is the distance in pixels from that prediction to the cluster's
  centre, plus twice how far apart the two models move the cluster's centre over the new window (so
  that of two nearby clusters the one moving alike wins). Pairs costing more than the gate, 10 px plus
  the longer side of the larger box, never match; the others are assigned by the
  Hungarian algorithm (:func:`scipy.optimize.linear_sum_assignment`), least total cost.
* **New ids**: a cluster left unmatched gets the next unused id; ids grow and are never reused, even
  after their object has vanished. Only the previous window is remembered: an object missed for one
  window comes back with a new id.
* **Shared motion** (:func:`~evseg_torch.motion.shared.shared_motion_groups`): which clusters move
  alike, as level two prices them; a background that the graph cut split in two is one group.

The tracker's whole state is the previous window's :class:`TrackedClusters` (ids, centres, boxes,
models, ``t_ref``) and the next unused id, i.e. what ``models.jsonl`` stores per window
(``object_ids``, ``centres``, ``boxes``, ``models``, ``t_ref``) and one plus the largest id written: a
resumed run restores it exactly from the stopped run's rows (:meth:`TrackedClusters.from_record`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evseg_torch.errors import ShapeError
from evseg_torch.motion.shared import shared_motion_groups

__all__ = [
    "BACKGROUND_COVER",
    "ObjectTracker",
    "TrackedClusters",
    "describe_clusters",
    "find_background",
    "match_objects",
    "shared_motion_groups",
    "window_duration",
]

BACKGROUND_COVER = 0.5  # the background's compensated box covers at least this fraction of the sensor
GATE_PX = 10.0  # px: least gate of a match
# The gate's size term and the motion weight were chosen on streamed scenes of the hard family
# (benchmarks/bench_ids.py), where median centres with them keep more ids than box centres, the distance
# alone or a smaller gate.
GATE_SIZE = 1.0  # of the larger box's longer side, added to the gate
MOTION_WEIGHT = 2.0  # of the models' difference over the window, against the distance (both px)
_QUANTILES = (0.02, 0.5, 0.98)  # a box's low edges, a centre, a box's high edges


@dataclass(frozen=True)
class TrackedClusters:
    """The clusters of one window as the tracker sees them.

    Attributes:
        ids: object id of each cluster, int64 :math:`(K,)`.
        centres: median ``[x, y]`` of each cluster's compensated events, px, float64 :math:`(K, 2)`;
            NaN rows for clusters without events.
        boxes: ``[x, y, w, h]`` of each cluster's compensated events, px, float64 :math:`(K, 4)`; NaN
            rows for clusters without events.
        models: each cluster's model, float64 :math:`(K, P)`.
        t_ref: the window's reference time, seconds.
    """

    ids: np.ndarray
    centres: np.ndarray
    boxes: np.ndarray
    models: np.ndarray
    t_ref: float

    @classmethod
    def from_record(cls, record: dict) -> TrackedClusters:
        """The clusters of a ``models.jsonl`` row (``object_ids``, ``centres``, ``boxes``, ``models``,
        ``t_ref``; ``null`` for the centre and box of a cluster without events)."""
        n_params = len(record["parameters"])
        return cls(
            ids=np.asarray(record["object_ids"], dtype=np.int64),
            centres=_rows(record["centres"], 2),
            boxes=_rows(record["boxes"], 4),
            models=np.asarray(record["models"], dtype=np.float64).reshape(-1, n_params),
            t_ref=float(record["t_ref"]),
        )


def describe_clusters(labels, warped_xy, n_clusters: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each cluster's event count, and the centre and box of its compensated events.

    Args:
        labels: cluster of each event, int :math:`(N,)`; negative for none.
        warped_xy: each event warped to ``t_ref`` by its cluster's model, :math:`(N, 2)`.
        n_clusters: K.

    Returns:
        ``(counts (K,) int64, centres (K, 2) float64, boxes (K, 4) float64)``: centres the median of x
        and y, boxes ``[x, y, w, h]`` from their 2nd to their 98th percentile; NaN for a cluster
        without events.
    """
    labels = np.asarray(labels, dtype=np.int64)
    warped_xy = np.asarray(warped_xy, dtype=np.float64)
    if labels.ndim != 1 or warped_xy.shape != (len(labels), 2):
        raise ShapeError(
            f"labels (N,) and warped_xy (N, 2) must match, got {labels.shape}, {warped_xy.shape}"
        )
    counts = np.bincount(labels[labels >= 0], minlength=n_clusters)[:n_clusters]
    centres, boxes = np.full((n_clusters, 2), np.nan), np.full((n_clusters, 4), np.nan)
    order = np.argsort(labels, kind="stable")
    starts = np.searchsorted(labels[order], np.arange(n_clusters + 1))
    for k in range(n_clusters):
        xy = warped_xy[order[starts[k] : starts[k + 1]]]
        if len(xy):
            low, centres[k], high = np.quantile(xy, _QUANTILES, axis=0)
            boxes[k] = [low[0], low[1], high[0] - low[0], high[1] - low[1]]
    return counts, centres, boxes


def find_background(counts: np.ndarray, boxes: np.ndarray, sensor_size: tuple[int, int]) -> int | None:
    """The background cluster: the one of most events (the first on ties), if its box covers at least
    :data:`BACKGROUND_COVER` of the sensor; else ``None``."""
    if len(counts) == 0 or counts.max() == 0:
        return None
    largest = int(np.argmax(counts))
    height, width = sensor_size
    area = boxes[largest, 2] * boxes[largest, 3]
    return largest if area >= BACKGROUND_COVER * height * width else None


def match_objects(
    previous: TrackedClusters | None,
    centres: np.ndarray,
    boxes: np.ndarray,
    models: np.ndarray,
    t_ref: float,
    duration: float,
    background: int | None,
    next_id: int,
    motion,
    gate_px: float = GATE_PX,
    gate_size: float = GATE_SIZE,
    motion_weight: float = MOTION_WEIGHT,
) -> tuple[np.ndarray, int]:
    """Object ids of a window's clusters, continuing the previous window's (module doc).

    Args:
        previous: the previous window's clusters, or ``None`` for the first window.
        centres: this window's compensated centres, :math:`(K, 2)` (NaN: no events).
        boxes: this window's compensated boxes ``[x, y, w, h]``, :math:`(K, 4)`.
        models: this window's models, :math:`(K, P)`.
        t_ref: this window's reference time, seconds.
        duration: this window's time span, seconds (for the motion term of the cost).
        background: this window's background cluster (:func:`find_background`), or ``None``.
        next_id: the least id never given yet, at least 1.
        motion: the :class:`~evseg_torch.motion.MotionModel` of ``models``.
        gate_px, gate_size: the gate: a match costs at most ``gate_px + gate_size * side`` px, ``side``
            the longer side of the larger of the two boxes.
        motion_weight: weight of the models' difference (px over the window) against the distance.

    Returns:
        ``(ids (K,) int64, next_id)``: 0 for the background, a previous object's id for its match, new
        ids from ``next_id`` up (in cluster order) for the rest.
    """
    centres = np.asarray(centres, dtype=np.float64)
    boxes = np.asarray(boxes, dtype=np.float64)
    models = np.asarray(models, dtype=np.float64)
    ids = np.full(len(boxes), -1, dtype=np.int64)
    if background is not None:
        ids[background] = 0
    candidates = np.flatnonzero((ids < 0) & np.isfinite(centres).all(axis=1))
    if previous is not None and len(candidates):
        objects = np.flatnonzero((previous.ids > 0) & np.isfinite(previous.centres).all(axis=1))
        if len(objects):
            now = TrackedClusters(ids, centres, boxes, models, t_ref)
            rows, cols, cost, gate = _costs(
                previous, objects, now, candidates, duration, motion, gate_px, gate_size, motion_weight
            )
            for row, col in zip(rows, cols, strict=True):
                if cost[row, col] <= gate[row, col]:
                    ids[candidates[col]] = previous.ids[objects[row]]
    for k in np.flatnonzero(ids < 0):
        ids[k], next_id = next_id, next_id + 1
    return ids, next_id


def _costs(previous, objects, now, candidates, duration, motion, gate_px, gate_size, motion_weight):
    """The Hungarian assignment of previous objects (rows) to candidate clusters (columns), with the
    cost and gate of every pair."""
    elapsed = now.t_ref - previous.t_ref
    predicted = np.stack(
        [motion.predict(previous.centres[i : i + 1], elapsed, previous.models[i])[0] for i in objects]
    )
    centres, models = now.centres[candidates], now.models
    distance = np.linalg.norm(predicted[:, None] - centres[None], axis=-1)
    # Both models' velocity at each candidate's centre: how far apart they move it over the window.
    theirs = motion.velocity(centres, previous.models[objects])  # (objects, candidates, 2)
    ours = np.stack([motion.velocity(centres[j : j + 1], models[k])[0] for j, k in enumerate(candidates)])
    apart = duration * np.linalg.norm(theirs - ours[None], axis=-1)
    cost = distance + motion_weight * apart
    before, after = previous.boxes[objects], now.boxes[candidates]
    side = np.maximum(before[:, None, 2:].max(axis=-1), after[None, :, 2:].max(axis=-1))
    gate = gate_px + gate_size * side
    # Pairs beyond the gate may still be assigned; they are refused afterwards, but priced so high that
    # the assignment never trades a feasible pair for them.
    priced = np.where(cost <= gate, cost, gate.max() + cost.max() + 1e6)
    # scipy loads on first use, so that ``import evseg_torch`` (whose results reader imports this
    # module) stays light.
    from scipy.optimize import linear_sum_assignment

    rows, cols = linear_sum_assignment(priced)
    return rows, cols, cost, gate


class ObjectTracker:
    """Give the clusters of consecutive windows object ids that persist (module doc).

    Feed it the windows in time order; its ids depend on nothing else (not on batches or workers).

    Args:
        motion: the :class:`~evseg_torch.motion.MotionModel` of the windows' models.
        previous: the last window's clusters, to carry on from (a stopped run's last
            :meth:`TrackedClusters.from_record`); ``None`` to start.
        next_id: the least id not given yet (one more than the largest given so far).

    Examples:
        >>> from evseg_torch.motion import make_motion_model
        >>> tracker = ObjectTracker(make_motion_model("translation", (90, 120)))
        >>> tracker.next_id
        1
    """

    def __init__(self, motion, previous: TrackedClusters | None = None, next_id: int = 1) -> None:
        self.motion = motion
        self.previous = previous
        self.next_id = next_id

    def update(self, segmentation) -> np.ndarray:
        """The object ids of the next window's clusters, int64 :math:`(K,)` (row ``k``: cluster ``k``).

        Args:
            segmentation: a :class:`~evseg_torch.pipeline.Segmentation`.
        """
        labels = _numpy(segmentation.labels).astype(np.int64)
        models = _numpy(segmentation.models).astype(np.float64)
        centres, boxes = segmentation.centres, segmentation.boxes
        counts = np.bincount(labels[labels >= 0], minlength=len(models))
        ids, self.next_id = match_objects(
            self.previous,
            centres,
            boxes,
            models,
            float(segmentation.t_ref),
            window_duration(segmentation.events),
            find_background(counts, boxes, segmentation.sensor_size),
            self.next_id,
            self.motion,
        )
        self.previous = TrackedClusters(ids, centres, boxes, models, float(segmentation.t_ref))
        return ids


def window_duration(events: np.ndarray) -> float:
    """A window's time span in seconds: from its first event to its last (0 without events)."""
    times = events["t"]
    return 1e-6 * float(times[-1] - times[0]) if len(times) else 0.0


def _rows(values: list, width: int) -> np.ndarray:
    """float64 :math:`(K, width)` of JSON rows, ``null`` rows as NaN."""
    return np.array([[np.nan] * width if row is None else row for row in values], dtype=np.float64).reshape(
        -1, width
    )


def _numpy(value) -> np.ndarray:
    """A NumPy array of a NumPy array or a torch tensor (without importing torch)."""
    return value.detach().cpu().numpy() if hasattr(value, "detach") else np.asarray(value)

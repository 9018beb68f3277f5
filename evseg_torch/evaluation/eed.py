"""The EED detection-rate protocol (Mitrokhin et al., IROS 2018; reference §3.1), stated exactly.

For each ground-truth box at time ``t_b``:

1. Segment the window of ``window_ms`` centred on ``t_b`` (the boxes are drawn on APS frames, so a
   centred window is the fair one). The reference time, to which every cluster is compensated, is
   ``t_ref = t_b`` (``reference="box"``, the default), or the window's first event
   (``reference="window_start"``): the convention of EMSGC's output and of the IROS paper's figures,
   which puts the compensated clusters half a window before ``t_b``. On EED's ``occlusions`` the GT
   boxes themselves lag the events: the density of events inside the boxes peaks before the box stamps,
   about where the window-start convention compensates to. A window with fewer than ``min_events``
   events is *not evaluable* and reported separately (it counts in neither numerator nor denominator).
2. **Background rule**: the cluster holding the most events is the background (the ego-motion of a
   moving camera explains most events; EMSGC numbers clusters by size for the same reason).
3. Each other cluster's events are warped by its own model to ``t_ref``; the cluster's box is the
   bounding box of the pixels of its compensated count image (σ = 0) that hold more than
   ``min_count`` events (EMSGC's output rule, which drops isolated noise).
4. The GT box is matched to the non-background cluster whose box has the highest IoU with it; the
   object is **detected when that IoU > 0.5**. Three looser readings of the original protocol's "overlap
   by more than 50 %" are reported beside it for the same match: the intersection over the GT box's
   area; over the predicted box's area (under which a compensated object inside a larger GT box,
   drawn around a motion-blurred APS image, counts as detected); and the *nested* reading, the
   intersection over the smaller box's area with the two areas within 4x of each other
   (:func:`~.metrics.boxes_nested`: the object inside a blurred GT box counts, a cluster box
   spanning half the image around a small GT box does not).

Detection rate = detected / evaluable boxes.

**Why a box is missed** (beyond the protocol; the nested reading): the events compensated into the GT box
(``Segmentation.warped_xy`` inside it) are counted per cluster, and the cluster holding most of them is
the box's *owner*. A box not detected is ``background`` when its owner is the background cluster,
``merged`` when its owner also owns another GT box of the same time (one cluster holds two objects),
``stretched`` when its owner is its own cluster but that cluster's box does not nest with it (foreign or
missing events), ``unassigned`` when no event lands in it. Level one's part: the feature tracks whose
midpoint (their position at the window's centre, the box time) lies in the GT box, and whether one of
level one's clusters of tracks has most of its tracks there (a model of the box's own). Boxes of the
same time are scored on one segmentation of their common window.

**Objects apart in a stream** (:func:`separate_in_stream`, beyond the protocol): in a stream of windows
(``evseg segment``), a box time with two or more GT boxes is *in view* when a segmented window holds it
and each box holds at least ``min_events`` (1) of the window's events within ``near_ms`` of its time (an
object that does not fire is not in an event camera's view); there each box's owner is the cluster holding
most of those events (raw positions: no model is trusted to place them), and the objects are *apart* when
no owner is the background (object id 0) and no two are the same.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from evseg_torch.config import SegmenterConfig
from evseg_torch.errors import ConfigError, ReaderError
from evseg_torch.evaluation.metrics import box_intersection, box_iou, box_of_points, boxes_nested
from evseg_torch.events.images import event_counts
from evseg_torch.io import load_eed_boxes, load_events
from evseg_torch.level_two.image.warp import warp_events
from evseg_torch.motion import MotionModel
from evseg_torch.pipeline import CascadedSegmenter

EED_SENSOR_SIZE = (180, 240)  # DAVIS240; the boxes are drawn on its 240x180 APS frames
REFERENCES = ("box", "window_start")
BOX_OUTCOMES = ("detected", "background", "merged", "stretched", "unassigned")
"""What became of a GT box under the nested reading (module docstring)."""

PAPER_TABLE_I = {
    # Detection rates (%) from the IROS 2021 paper's Table I: EED, EMSMC, EMSGC, ours (reference §3.1, §4).
    "what_is_background": {"EED": 89.21, "EMSMC": 100.0, "EMSGC": 100.0, "IROS 2021": 100.0},
    "occlusions": {"EED": 90.83, "EMSMC": 92.31, "EMSGC": 100.0, "IROS 2021": 100.0},
    # The paper's figures are for the whole recording; ../shared holds its first half.
    "multiple_objects_2objs_first_half": {"EED": 87.32, "EMSMC": 96.77, "EMSGC": 0.0, "IROS 2021": 95.67},
}


@dataclass(frozen=True)
class EedSequence:
    """One EED sequence with events and boxes in one time base (seconds)."""

    name: str
    events: np.ndarray
    box_times_s: np.ndarray
    boxes: np.ndarray
    sensor_size: tuple[int, int] = EED_SENSOR_SIZE


def load_eed_sequence(folder: str | Path) -> EedSequence:
    """Load an EED folder: ``events.txt`` / ``events.npz`` and ``boundingbox.txt``.

    Where a ``boundingbox_rel.txt`` exists (a cut whose events start at the first box, see the folder's
    README), its relative box times go with the relative ``events.npz``; otherwise the absolute times of
    ``boundingbox.txt`` go with the absolute ``events.txt``.
    """
    folder = Path(folder)
    relative = folder / "boundingbox_rel.txt"
    if relative.is_file():
        times, boxes = load_eed_boxes(relative)
        events_file = folder / "events.npz" if (folder / "events.npz").is_file() else folder / "events.txt"
    else:
        times, boxes = load_eed_boxes(folder / "boundingbox.txt")
        events_file = folder / "events.txt"
    if not events_file.is_file():
        raise ReaderError(f"{folder}: no events file ({events_file.name}) for the EED protocol")
    name = folder.name.removeprefix("eed_")
    return EedSequence(name, load_events(events_file, sensor_size=EED_SENSOR_SIZE), times, boxes)


@dataclass(frozen=True)
class BoxResult:
    """One ground-truth box: its time, whether it was evaluable, the match and its scores, and why it was
    missed (``outcome``, one of :data:`BOX_OUTCOMES`; ``""`` when not evaluable) with level one's tracks
    on it and whether a model of level one's pool was its own (module docstring)."""

    t_s: float
    gt_box: np.ndarray
    evaluable: bool
    n_events: int
    predicted_box: np.ndarray
    iou: float
    intersection_over_gt: float
    n_clusters: int
    intersection_over_predicted: float = 0.0
    outcome: str = ""
    tracks: int = 0
    own_model: bool = False

    @property
    def detected(self) -> bool:
        return self.evaluable and self.iou > 0.5

    @property
    def detected_nested(self) -> bool:
        """The nested reading: the matched and the GT box nest (:func:`~.metrics.boxes_nested`)."""
        return self.evaluable and bool(boxes_nested(self.predicted_box, self.gt_box))


def cluster_boxes(segmentation, min_count: float = 2.0) -> dict[int, np.ndarray]:
    """``[x, y, w, h]`` box of each non-background cluster's compensated events (rule of the module doc)."""
    height, width = segmentation.sensor_size
    labels = segmentation.labels
    if len(labels) == 0:
        return {}
    sizes = np.bincount(labels[labels >= 0], minlength=segmentation.n_clusters)
    background = int(np.argmax(sizes))
    counts = event_counts(segmentation.warped_xy, (height, width), labels, n_labels=segmentation.n_clusters)
    boxes = {}
    for cluster, image in enumerate(counts):
        dense = np.argwhere(image > min_count)
        if cluster != background and len(dense):
            boxes[cluster] = box_of_points(dense[:, ::-1].astype(np.float64))
    return boxes


def evaluate_boxes(
    segmenter,
    events: np.ndarray,
    box_times_s: np.ndarray,
    boxes: np.ndarray,
    *,
    window_ms: float,
    min_events: int = 500,
    min_count: float = 2.0,
    reference: str = "box",
    progress: bool = False,
    on_window: Callable[[BoxResult, object], None] | None = None,
) -> list[BoxResult]:
    """Run the protocol on one sequence.

    Args:
        segmenter: ``segmenter(events, t_ref=seconds) -> Segmentation``.
        events: canonical events, in the same time base as ``box_times_s``.
        box_times_s: GT box times in seconds, :math:`(M,)`.
        boxes: GT boxes ``[x, y, w, h]``, :math:`(M, 4)`.
        window_ms: length of the window centred on each box time.
        min_events: windows with fewer events are not evaluable.
        min_count: a pixel of a cluster's compensated image belongs to its box above this count.
        reference: the time the clusters are compensated to, ``"box"`` (the box time) or
            ``"window_start"`` (the window's first event, EMSGC's convention); see the module doc.
        progress: show a progress bar.
        on_window: called with each evaluable box's result and its window's segmentation, e.g. to
            draw it (``evseg evaluate eed --figures``).

    Raises:
        ConfigError: ``reference`` is not one of :data:`REFERENCES`.
    """
    from tqdm.auto import tqdm

    if reference not in REFERENCES:
        raise ConfigError(f"reference must be one of {REFERENCES}, got {reference!r}")
    half_us = round(window_ms * 500)
    results = [None] * len(boxes)
    times = np.asarray(box_times_s, dtype=np.float64)
    groups = [np.flatnonzero(times == t_s) for t_s in dict.fromkeys(times.tolist())]
    for group in tqdm(groups, desc="box times", disable=not progress):
        t_s = float(times[group[0]])
        centre = round(t_s * 1e6)
        begin, end = np.searchsorted(events["t"], [centre - half_us, centre + half_us], side="left")
        window = events[begin:end]
        if len(window) < min_events:
            for index in group:
                empty = BoxResult(t_s, boxes[index], False, len(window), np.full(4, np.nan), 0.0, 0.0, 0)
                results[index] = empty
            continue
        t_ref = t_s if reference == "box" else int(window["t"][0]) * 1e-6
        segmentation = segmenter(window, t_ref=t_ref)
        scored = _score_boxes(segmentation, t_s, boxes[group], min_count)
        for index, result in zip(group, scored, strict=True):
            results[index] = result
            if on_window is not None:
                on_window(result, segmentation)
    return results


def evaluate_stream_boxes(
    segmentations, box_times_s: np.ndarray, boxes: np.ndarray, motion: MotionModel, min_count: float = 2.0
) -> list[BoxResult]:
    """The protocol on a stream's windows (``evseg segment``; beyond the protocol, module docstring).

    Each GT box is scored on the streamed window that holds its time, with that window's clusters
    compensated to the box time (their models moved from the window's reference time), so that a stream
    and the same windows segmented cold are scored alike. A box time no window holds is not evaluable.

    Args:
        segmentations: the stream's windows (:class:`~evseg_torch.pipeline.Segmentation`), in the time
            base of ``box_times_s``.
        box_times_s: GT box times in seconds, :math:`(M,)`.
        boxes: GT boxes ``[x, y, w, h]``, :math:`(M, 4)`.
        motion: the motion model of the windows' models.
        min_count: a pixel of a cluster's compensated image belongs to its box above this count.

    Returns:
        One :class:`BoxResult` per GT box.
    """
    times = np.asarray(box_times_s, dtype=np.float64)
    boxes = np.asarray(boxes, dtype=np.float64)
    results = [None] * len(boxes)
    for t_s in dict.fromkeys(times.tolist()):
        group = np.flatnonzero(times == t_s)
        window = _holding(segmentations, t_s)
        if window is None:
            scored = [BoxResult(t_s, box, False, 0, np.full(4, np.nan), 0.0, 0.0, 0) for box in boxes[group]]
        else:
            scored = _score_boxes(_compensated_to(window, t_s, motion), t_s, boxes[group], min_count)
        for index, result in zip(group, scored, strict=True):
            results[index] = result
    return results


def _holding(segmentations, t_s: float):
    """The first window whose events span the time ``t_s`` (seconds), or ``None``."""
    centre = round(t_s * 1e6)
    return next(
        (s for s in segmentations if len(s.events) and s.events["t"][0] <= centre <= s.events["t"][-1]),
        None,
    )


def _compensated_to(segmentation, t_s: float, motion: MotionModel):
    """The segmentation with every event warped by its cluster's model to ``t_s`` (seconds)."""
    events = segmentation.events
    xy = torch.as_tensor(np.stack([events["x"], events["y"]], axis=1), dtype=torch.float64)
    t = torch.as_tensor((events["t"] - round(t_s * 1e6)) * 1e-6, dtype=torch.float64)
    labels = np.asarray(segmentation.labels)
    own = torch.as_tensor(np.asarray(segmentation.models)[np.maximum(labels, 0)], dtype=torch.float64)
    warped = warp_events(motion, xy[:, None], t[:, None], own)[:, 0].numpy()
    return replace(segmentation, warped_xy=warped, t_ref=t_s)


def _score_boxes(segmentation, t_s: float, gt_boxes: np.ndarray, min_count: float) -> list[BoxResult]:
    """Every GT box of one time scored on one window's segmentation (module docstring)."""
    n_events = len(segmentation.labels)
    candidates = cluster_boxes(segmentation, min_count)
    scored = [_match(t_s, box, n_events, segmentation.n_clusters, candidates) for box in gt_boxes]
    outcomes = box_outcomes(segmentation, gt_boxes, [result.detected_nested for result in scored])
    tracks, own_model = level_one_support(segmentation, gt_boxes)
    return [
        replace(result, outcome=outcome, tracks=int(count), own_model=bool(own))
        for result, outcome, count, own in zip(scored, outcomes, tracks, own_model, strict=True)
    ]


def _match(t_s: float, gt: np.ndarray, n_events: int, n_clusters: int, candidates: dict) -> BoxResult:
    """The GT box matched to the non-background cluster box of highest IoU, with its readings."""
    best_box, best_iou = np.full(4, np.nan), 0.0
    for box in candidates.values():
        iou = float(box_iou(box, gt))
        if iou > best_iou or np.isnan(best_box[0]):
            best_box, best_iou = box, iou
    intersection = float(box_intersection(best_box, gt)) if not np.isnan(best_box[0]) else 0.0
    return BoxResult(
        t_s,
        gt,
        True,
        n_events,
        best_box,
        best_iou,
        _ratio(intersection, gt[2] * gt[3]),
        n_clusters,
        _ratio(intersection, best_box[2] * best_box[3]),
    )


def _inside(xy: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Which positions :math:`(n, 2)` lie in the box ``[x, y, w, h]`` (edges included)."""
    x, y, w, h = box
    return (xy[:, 0] >= x) & (xy[:, 0] <= x + w) & (xy[:, 1] >= y) & (xy[:, 1] <= y + h)


def box_outcomes(segmentation, gt_boxes: np.ndarray, detected) -> list[str]:
    """What became of each GT box of one window (:data:`BOX_OUTCOMES`, module docstring).

    Args:
        segmentation: the window's :class:`~evseg_torch.pipeline.Segmentation` (its ``labels``,
            ``warped_xy`` and ``n_clusters`` are read).
        gt_boxes: the window's GT boxes ``[x, y, w, h]``, :math:`(k, 4)`.
        detected: whether each box was detected (the nested reading), :math:`(k,)`.

    Returns:
        One outcome per box.
    """
    labels, n_clusters = segmentation.labels, segmentation.n_clusters
    assigned = labels >= 0
    background = int(np.argmax(np.bincount(labels[assigned], minlength=n_clusters))) if assigned.any() else -1
    owners = []
    for box in gt_boxes:
        inside = assigned & _inside(segmentation.warped_xy, box)
        owners.append(int(np.bincount(labels[inside], minlength=n_clusters).argmax()) if inside.any() else -1)
    outcomes = []
    for owner, hit in zip(owners, detected, strict=True):
        if hit:
            outcomes.append("detected")
        elif owner < 0:
            outcomes.append("unassigned")
        elif owner == background:
            outcomes.append("background")
        elif owners.count(owner) > 1:
            outcomes.append("merged")
        else:
            outcomes.append("stretched")
    return outcomes


def level_one_support(segmentation, gt_boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Level one's tracks on each GT box of one window, and whether a model of its pool is the box's own.

    A track is on a box when its midpoint (its position at the window's centre) lies in it; a cluster of
    level one's tracks (``feature_labels`` >= 0) is a box's own when most of its tracks are on the box.

    Returns:
        The tracks on each box, int64 :math:`(k,)`, and whether some cluster is its own, bool :math:`(k,)`.
    """
    tracks = segmentation.feature_tracks
    middle = (tracks.src + tracks.dst) / 2
    labels = np.asarray(segmentation.feature_labels)
    clustered = labels >= 0
    sizes = np.bincount(labels[clustered]) if clustered.any() else np.zeros(0, dtype=np.int64)
    counts, own = np.zeros(len(gt_boxes), dtype=np.int64), np.zeros(len(gt_boxes), dtype=bool)
    for k, box in enumerate(gt_boxes):
        on_box = _inside(middle, box)
        counts[k] = np.count_nonzero(on_box)
        if len(sizes):
            there = np.bincount(labels[on_box & clustered], minlength=len(sizes))
            own[k] = bool(np.any(2 * there > sizes))
    return counts, own


def evaluate_sequence(
    sequence: EedSequence,
    config: SegmenterConfig,
    *,
    window_ms: float | None = None,
    reference: str = "box",
    progress: bool = False,
    on_window: Callable[[BoxResult, object], None] | None = None,
    device: str = "cpu",
) -> list[BoxResult]:
    """Run the protocol on a sequence with a :class:`~evseg_torch.pipeline.CascadedSegmenter`.

    Args:
        sequence: from :func:`load_eed_sequence`.
        config: the segmenter's config (the bundled ``eed.yaml`` for the paper's figures); its
            ``window.min_events`` sets which windows are evaluable.
        window_ms: window length; default ``config.window.window_ms``.
        reference, progress, on_window: as in :func:`evaluate_boxes`.
        device: torch device of level two.

    Returns:
        One :class:`BoxResult` per GT box.
    """
    return evaluate_boxes(
        CascadedSegmenter(sequence.sensor_size, config).to(device),
        sequence.events,
        sequence.box_times_s,
        sequence.boxes,
        window_ms=window_ms or config.window.window_ms,
        min_events=config.window.min_events,
        reference=reference,
        progress=progress,
        on_window=on_window,
    )


def _ratio(intersection: float, area: float) -> float:
    """``intersection / area``, 0 for an empty or missing box."""
    return intersection / float(area) if area > 0 else 0.0


def detection_rate(results: list[BoxResult]) -> dict[str, float]:
    """Detection rate (IoU > 0.5), the three overlap readings (``detection_rate_overlap``: intersection
    over GT area > 0.5, ``detection_rate_over_predicted``: over predicted area > 0.5,
    ``detection_rate_nested``: the boxes nest) and the mean IoU, over the evaluable boxes; how many boxes
    were missed for each reason (``missed_<outcome>``, :data:`BOX_OUTCOMES`) and how many had level one's
    tracks on them and a model of their own (``boxes_with_tracks``, ``boxes_with_own_model``)."""
    evaluable = [r for r in results if r.evaluable]
    if not evaluable:
        return {"boxes": len(results), "evaluable": 0, "detection_rate": float("nan")}
    return {
        "boxes": len(results),
        "evaluable": len(evaluable),
        "detected": sum(r.detected for r in evaluable),
        "detection_rate": 100.0 * sum(r.detected for r in evaluable) / len(evaluable),
        "detection_rate_overlap": 100.0 * float(np.mean([r.intersection_over_gt > 0.5 for r in evaluable])),
        "detection_rate_over_predicted": 100.0
        * float(np.mean([r.intersection_over_predicted > 0.5 for r in evaluable])),
        "detection_rate_nested": 100.0 * float(np.mean([r.detected_nested for r in evaluable])),
        "mean_iou": float(np.mean([r.iou for r in evaluable])),
        **{f"missed_{outcome}": sum(r.outcome == outcome for r in evaluable) for outcome in BOX_OUTCOMES[1:]},
        "boxes_with_tracks": sum(r.tracks > 0 for r in evaluable),
        "boxes_with_own_model": sum(r.own_model for r in evaluable),
    }


def separate_in_stream(
    segmentations, box_times_s: np.ndarray, boxes: np.ndarray, near_ms: float = 3.0, min_events: int = 1
):
    """How many box times with several GT boxes a stream holds, and at how many its objects are apart
    (module docstring).

    Args:
        segmentations: the stream's windows (:class:`~evseg_torch.pipeline.Segmentation`, with ``events``
            and ``object_ids``), in the time base of ``box_times_s``.
        box_times_s: GT box times in seconds, :math:`(M,)`.
        boxes: GT boxes ``[x, y, w, h]``, :math:`(M, 4)`.
        near_ms: events within this many milliseconds of a box time are its events.
        min_events: fewest events of each box for its time to be in view.

    Returns:
        ``(in_view, apart)``.
    """
    times = np.asarray(box_times_s, dtype=np.float64)
    in_view = apart = 0
    for t_s in dict.fromkeys(times.tolist()):
        group = np.flatnonzero(times == t_s)
        centre = round(t_s * 1e6)
        window = _holding(segmentations, t_s)
        if len(group) < 2 or window is None:
            continue
        near = np.abs(window.events["t"] - centre) <= near_ms * 1e3
        xy = np.stack([window.events["x"], window.events["y"]], axis=1).astype(np.float64)
        inside = [near & _inside(xy, boxes[index]) & (window.labels >= 0) for index in group]
        if min(np.count_nonzero(events) for events in inside) < min_events:
            continue
        in_view += 1
        owners = [
            int(window.object_ids[np.bincount(window.labels[events], minlength=window.n_clusters).argmax()])
            for events in inside
        ]
        apart += int(0 not in owners and len(set(owners)) == len(owners))
    return in_view, apart

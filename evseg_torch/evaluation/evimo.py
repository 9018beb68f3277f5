"""The EV-IMO IoU protocol (Mitrokhin et al., IROS 2019; reference §3.2), stated exactly.

For each mask of the sequence, at time ``t`` (seconds, the events' time base):

1. Segment the window of ``window_ms`` **centred** on ``t`` (as in :mod:`~evseg_torch.evaluation.eed`: the
   masks are rendered at ``t``, so the window's events straddle it), with the reference time ``t_ref = t``. A
   window with fewer than ``min_events`` events, and a mask with no object pixel, are *not evaluated*: they
   are reported with their reason and left out of every mean.
2. **Background rule** (as in :mod:`~evseg_torch.evaluation.eed`): the cluster holding the most events is the
   background; the other clusters are the independently moving objects (IMOs).
3. **Convex-hull mask IoU** (EMSGC, TNNLS Eq. 11, and the IROS 2021 paper): each IMO cluster's events
   are warped by its own model to ``t`` (``Segmentation.warped_xy``); the pixels of its compensated count
   image (σ = 0, warped positions rounded) holding more than ``min_count`` events are kept (EMSGC's
   output rule, which drops isolated noise), and the cluster's dense mask is the convex hull of those
   pixels. The predicted mask ``P`` is the union of the IMO clusters' hulls, the ground-truth mask
   ``G`` is the EV-IMO mask's object pixels (any id > 0), and the score is ``|P ∩ G| / |P ∪ G|``.
4. **Event-wise IoU** (MOMS, 0-MMS, SpikeMS): on the window's raw, unwarped event pixels,
   ``P_e`` is the set of pixels holding at least one event of an IMO cluster and ``G_e`` the set of
   pixels holding at least one event and lying inside ``G``; the score is ``|P_e ∩ G_e| / |P_e ∪ G_e|``
   (the IoU of the binary 2-D occupancy images of predicted-IMO events and GT-masked events). It is
   NaN when both sets are empty (no event on the object and none predicted as IMO).

5. **Learned maskers' metrics** (uzh-rpg/event_suppression ``evsup/metrics.py``), so that learned
   baselines' tables compare: the predicted dynamic mask is the convex-hull mask ``P`` of step 3 (so the
   *pixel IoU of the dynamic class* is the convex-hull IoU), ``mIoU`` is the mean of the dynamic IoU and
   the background IoU ``|~P ∩ ~G| / |~P ∪ ~G|``, ``pIoU`` is the dynamic IoU over the pixels holding at
   least one event of the window, and ``SR@0.5`` is the fraction of evaluated frames whose convex-hull IoU
   is at least 0.5.
6. **Event IoU** (event level, per frame containing an object, as EVIMO2 evaluations report it): the IoU of
   the window's events labelled IMO and the window's events on ``G`` pixels, counting events, not pixels.

A sequence's score is the mean over its evaluated frames of each IoU. The two definitions give
different numbers (the convex hull fills the object's interior, the event-wise IoU counts only pixels
with events), so only the convex-hull IoU compares with the IROS 2021 / EMSGC tables.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evseg_torch.errors import ShapeError
from evseg_torch.evaluation.metrics import (
    convex_hull_mask,
    event_iou,
    event_pixel_iou,
    mask_iou,
    mean_iou,
    success_rate,
)
from evseg_torch.events.images import event_counts

CONVEX_HULL_IOU = (
    "convex-hull mask IoU (IROS 2021 / EMSGC): union of the convex hulls of the IMO clusters' "
    "motion-compensated events at the mask time vs the EV-IMO mask"
)
EVENT_WISE_IOU = (
    "event-wise IoU (MOMS / 0-MMS / SpikeMS): pixel occupancy of the events predicted as IMO vs "
    "that of the events inside the EV-IMO mask"
)
MIOU = "mIoU (event_suppression): mean of the dynamic (convex-hull mask) and background IoUs"
PIOU = "pIoU (event_suppression): the convex-hull mask IoU over the pixels holding events of the window"
SR_AT_05 = "SR@0.5 (event_suppression): fraction of evaluated frames with convex-hull mask IoU >= 0.5"
EVENT_IOU = "event IoU (EVIMO2): events labelled IMO vs events on object pixels, counted per event"

EVALUATED, EMPTY_GT, TOO_FEW_EVENTS = "evaluated", "empty_gt", "too_few_events"


@dataclass(frozen=True)
class FrameResult:
    """One EV-IMO mask: its time, whether it was evaluated (``status``) and its two IoUs.

    Attributes:
        t_s: the mask's time in seconds.
        status: ``"evaluated"``, ``"empty_gt"`` (the mask holds no object) or ``"too_few_events"``.
        n_events: events in the window.
        n_clusters: clusters holding events of the window (0 when it was not segmented).
        gt_pixels: object pixels of the mask.
        predicted_pixels: pixels of the predicted convex-hull mask.
        convex_hull_iou: the convex-hull mask IoU; NaN unless evaluated.
        event_wise_iou: the event-wise IoU; NaN unless evaluated, or when it is undefined.
        miou: mean of the dynamic and background pixel IoUs; NaN unless evaluated.
        piou: the convex-hull mask IoU over the pixels holding events; NaN unless evaluated or undefined.
        event_iou: the event-level IoU; NaN unless evaluated, or when it is undefined.
    """

    t_s: float
    status: str
    n_events: int
    n_clusters: int
    gt_pixels: int
    predicted_pixels: int
    convex_hull_iou: float
    event_wise_iou: float
    miou: float = float("nan")
    piou: float = float("nan")
    event_iou: float = float("nan")

    @property
    def evaluated(self) -> bool:
        return self.status == EVALUATED


def background_cluster(labels: np.ndarray) -> int:
    """The cluster holding the most events (``-1`` when no event is labelled); ties go to the lowest."""
    labels = np.asarray(labels)
    assigned = labels[labels >= 0]
    return int(np.argmax(np.bincount(assigned))) if len(assigned) else -1


def predicted_mask(
    warped_xy: np.ndarray, labels: np.ndarray, sensor_size: tuple[int, int], min_count: float = 2.0
) -> np.ndarray:
    """Union of the convex hulls of the IMO clusters' compensated events, :math:`(H, W)` bool.

    Args:
        warped_xy: each event warped by its cluster's model to the mask time, :math:`(N, 2)`.
        labels: cluster of each event, :math:`(N,)`, ``-1`` for unassigned; the largest cluster is the
            background and has no hull.
        sensor_size: ``(H, W)``.
        min_count: a compensated pixel counts when more than this many of the cluster's events land on
            it; warped events outside the image, or not finite, are dropped.

    Returns:
        The predicted IMO mask.
    """
    warped_xy, labels = np.asarray(warped_xy, dtype=np.float64), np.asarray(labels, dtype=np.int64)
    if warped_xy.shape != (len(labels), 2):
        raise ShapeError(f"warped_xy must be (N, 2) with labels (N,), got {warped_xy.shape}, {labels.shape}")
    imo = (labels >= 0) & (labels != background_cluster(labels))
    # Renumbered 0..K-1 so that the stack of count images holds only the IMO clusters present.
    clusters, owner = np.unique(labels[imo], return_inverse=True)
    counts = event_counts(warped_xy[imo], sensor_size, owner, n_labels=len(clusters))
    mask = np.zeros(sensor_size, dtype=bool)
    for image in counts:
        dense = np.argwhere(image > min_count)
        if len(dense):
            mask |= convex_hull_mask(dense[:, ::-1], sensor_size)
    return mask


def event_wise_iou(events: np.ndarray, is_imo: np.ndarray, gt_mask: np.ndarray) -> float:
    """IoU of the pixel occupancy of predicted-IMO events and of events inside the GT mask.

    Args:
        events: canonical events :math:`(N,)` inside the mask's ``(H, W)``.
        is_imo: whether each event is predicted to be on an IMO, bool :math:`(N,)`.
        gt_mask: the ground-truth object mask, bool :math:`(H, W)`.

    Returns:
        ``|P_e ∩ G_e| / |P_e ∪ G_e|`` (module doc), NaN when both sets are empty.
    """
    gt_mask = np.asarray(gt_mask, dtype=bool)
    is_imo = np.asarray(is_imo, dtype=bool)
    if is_imo.shape != events.shape:
        raise ShapeError(f"is_imo must be (N,) like the events, got {is_imo.shape} for {events.shape}")
    occupied = np.zeros(gt_mask.shape, dtype=bool)
    predicted = np.zeros(gt_mask.shape, dtype=bool)
    occupied[events["y"], events["x"]] = True
    predicted[events["y"][is_imo], events["x"][is_imo]] = True
    return mask_iou(predicted, occupied & gt_mask)


def evaluate_evimo(
    segmenter,
    sequence,
    *,
    window_ms: float,
    min_events: int = 500,
    min_count: float = 2.0,
    progress: bool = False,
) -> list[FrameResult]:
    """Run the protocol of the module doc on one sequence.

    Args:
        segmenter: ``segmenter(events, t_ref=seconds)`` returning an object with ``labels`` :math:`(N,)`
            and ``warped_xy`` :math:`(N, 2)` (a :class:`~evseg_torch.pipeline.Segmentation`), built for
            ``sequence.sensor_size``.
        sequence: an :class:`~evseg_torch.io.EvimoSequence` (events, masks and mask times).
        window_ms: length of the window centred on each mask time.
        min_events: windows with fewer events are not evaluated.
        min_count: EMSGC's noise rule for the compensated count image (see :func:`predicted_mask`).
        progress: show a progress bar.

    Returns:
        One :class:`FrameResult` per mask, in the sequence's order.
    """
    from tqdm.auto import tqdm

    events, half_us = sequence.events, round(window_ms * 500)
    centres = np.rint(np.asarray(sequence.mask_times_s, dtype=np.float64) * 1e6).astype(np.int64)
    begins = np.searchsorted(events["t"], centres - half_us, side="left")
    ends = np.searchsorted(events["t"], centres + half_us, side="left")
    results = []
    frames = zip(sequence.mask_times_s, sequence.masks, begins, ends, strict=True)
    for t_s, ids, begin, end in tqdm(list(frames), desc="frames", disable=not progress):
        gt = ids > 0
        gt_pixels, window = int(np.count_nonzero(gt)), events[begin:end]
        status = EMPTY_GT if gt_pixels == 0 else TOO_FEW_EVENTS if len(window) < min_events else EVALUATED
        if status != EVALUATED:
            results.append(FrameResult(float(t_s), status, len(window), 0, gt_pixels, 0, np.nan, np.nan))
            continue
        segmentation = segmenter(window, t_ref=float(t_s))
        labels = np.asarray(segmentation.labels)
        hull = predicted_mask(segmentation.warped_xy, labels, sequence.sensor_size, min_count)
        is_imo = (labels >= 0) & (labels != background_cluster(labels))
        occupied = np.zeros(sequence.sensor_size, dtype=bool)
        occupied[window["y"], window["x"]] = True
        results.append(
            FrameResult(
                float(t_s),
                EVALUATED,
                len(window),
                len(np.unique(labels[labels >= 0])),
                gt_pixels,
                int(np.count_nonzero(hull)),
                mask_iou(hull, gt),
                event_wise_iou(window, is_imo, gt),
                miou=mean_iou(hull, gt),
                piou=event_pixel_iou(hull, gt, occupied),
                event_iou=event_iou(is_imo, window, gt),
            )
        )
    return results


def summarize_evimo(results: list[FrameResult]) -> dict:
    """Frame counts and the mean of each IoU over the evaluated frames, each named with its definition.

    Returns:
        A flat, JSON-ready dict: ``frames``, ``evaluated``, ``empty_gt``, ``too_few_events``,
        ``convex_hull_iou`` and ``event_wise_iou`` (means in [0, 1], NaN without evaluated frames; the
        event-wise mean skips frames where it is undefined, counted in ``event_wise_frames``), the
        learned maskers' ``miou``, ``piou`` and ``sr_at_0_5``, and ``event_iou`` (means over the
        evaluated frames where each is defined), and each definition as ``<name>_definition``.
    """
    evaluated = [r for r in results if r.evaluated]
    hull = [r.convex_hull_iou for r in evaluated]
    event = [r.event_wise_iou for r in evaluated if not np.isnan(r.event_wise_iou)]

    def mean(name: str) -> float:
        values = [getattr(r, name) for r in evaluated if not np.isnan(getattr(r, name))]
        return float(np.mean(values)) if values else float("nan")

    return {
        "frames": len(results),
        "evaluated": len(evaluated),
        EMPTY_GT: sum(r.status == EMPTY_GT for r in results),
        TOO_FEW_EVENTS: sum(r.status == TOO_FEW_EVENTS for r in results),
        "convex_hull_iou": float(np.mean(hull)) if hull else float("nan"),
        "event_wise_iou": float(np.mean(event)) if event else float("nan"),
        "event_wise_frames": len(event),
        "miou": mean("miou"),
        "piou": mean("piou"),
        "sr_at_0_5": success_rate(hull),
        "event_iou": mean("event_iou"),
        "convex_hull_iou_definition": CONVEX_HULL_IOU,
        "event_wise_iou_definition": EVENT_WISE_IOU,
        "miou_definition": MIOU,
        "piou_definition": PIOU,
        "sr_at_0_5_definition": SR_AT_05,
        "event_iou_definition": EVENT_IOU,
    }

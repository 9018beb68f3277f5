"""Pure metric functions for motion segmentation (NumPy).

Definitions (reference §3):

* **Event-labelling accuracy**: the fraction of ground-truth events (noise excluded) whose predicted
  cluster is matched to their ground-truth layer, under the best one-to-one matching of clusters to
  layers (Hungarian algorithm on the overlap counts).
* **Per-object event IoU**: for each ground-truth object, ``|E_gt ∩ E_pred| / |E_gt ∪ E_pred|`` between its
  events and the events of the cluster matched to it (0 when no cluster is matched). This is the
  event-wise IoU that MOMS, 0-MMS and SpikeMS report.
* **Convex-hull mask IoU**: EMSGC's / the IROS paper's EV-IMO definition: a cluster's dense mask is the
  convex hull of its motion-compensated events; IoU of the union of object masks against the
  ground-truth mask.
* **Box IoU**: intersection over union of ``[x, y, w, h]`` boxes (EED's detection criterion: IoU > 0.5).
* **Dynamic-class metrics of learned maskers** (uzh-rpg/event_suppression, ``evsup/metrics.py``): with
  a predicted and a ground-truth binary *dynamic* mask, the dynamic IoU is :func:`mask_iou`; **mIoU** is
  the mean of the dynamic and the background (complement) IoUs, ignoring an undefined one
  (:func:`mean_iou`); **pIoU** is the IoU over the pixels that hold events only (:func:`event_pixel_iou`);
  **SR@0.5** is the fraction of frames whose dynamic IoU is at least 0.5, over the frames where it is
  defined (:func:`success_rate`).
* **Event IoU** (event level, as EVIMO2 evaluations report it per sequence): the IoU of the set of events
  predicted dynamic and the set of events on ground-truth object pixels (:func:`event_iou`).
* **Why an object is missed** (:func:`object_outcomes`): the cluster holding most of a missed object's
  events says what went wrong: the background's (``"background"``), one holding other objects' events too
  (``"merged"``), one holding too little of the object (``"split"``: the rest lies in other clusters), or
  its own cluster with a box that foreign or missing events move (``"stretched"``).
* **Nested boxes**: the intersection covers more than half of the smaller box and the larger box's area
  is at most 4 times the smaller's (a compensated object inside the larger GT box drawn around its
  motion-blurred image counts; a box swallowing half the image does not).
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from evseg_torch.errors import ShapeError


def match_clusters(pred: np.ndarray, gt: np.ndarray, ignore: int = -1) -> dict[int, int]:
    """Best one-to-one matching of predicted clusters to ground-truth layers by shared events.

    Args:
        pred: predicted cluster of each event, :math:`(N,)` (negative = unassigned).
        gt: ground-truth layer of each event, :math:`(N,)`; events labelled ``ignore`` are left out.

    Returns:
        ``{cluster: layer}`` for every matched pair with at least one shared event.
    """
    pred, gt = _labels(pred, gt)
    keep = (gt != ignore) & (pred >= 0)
    if not np.any(keep):
        return {}
    clusters, pred_idx = np.unique(pred[keep], return_inverse=True)
    layers, gt_idx = np.unique(gt[keep], return_inverse=True)
    overlap = np.zeros((len(clusters), len(layers)), dtype=np.int64)
    np.add.at(overlap, (pred_idx, gt_idx), 1)
    rows, cols = linear_sum_assignment(-overlap)
    return {int(clusters[r]): int(layers[c]) for r, c in zip(rows, cols, strict=True) if overlap[r, c] > 0}


def labelling_accuracy(pred: np.ndarray, gt: np.ndarray, ignore: int = -1) -> float:
    """Fraction of ground-truth events (``gt != ignore``) in the cluster matched to their layer."""
    pred, gt = _labels(pred, gt)
    keep = gt != ignore
    if not np.any(keep):
        return float("nan")
    mapping = match_clusters(pred, gt, ignore)
    mapped = (
        np.array([mapping.get(int(c), ignore - 1) for c in pred[keep]])
        if len(mapping)
        else np.full(int(keep.sum()), ignore - 1)
    )
    return float(np.mean(mapped == gt[keep]))


def per_object_iou(pred: np.ndarray, gt: np.ndarray, objects=None, ignore: int = -1) -> dict[int, float]:
    """Event IoU of each ground-truth object with the cluster matched to it.

    Args:
        objects: the layers to score; defaults to every layer except 0 (the background) and ``ignore``.

    Returns:
        ``{layer: IoU}``; events labelled ``ignore`` (noise) are left out of both sets.
    """
    pred, gt = _labels(pred, gt)
    mapping = {layer: cluster for cluster, layer in match_clusters(pred, gt, ignore).items()}
    pred, gt = pred[gt != ignore], gt[gt != ignore]
    if objects is None:
        objects = [int(v) for v in np.unique(gt) if v not in (0, ignore)]
    scores = {}
    for layer in objects:
        in_gt = gt == layer
        in_pred = pred == mapping[layer] if layer in mapping else np.zeros_like(in_gt)
        union = np.count_nonzero(in_gt | in_pred)
        scores[int(layer)] = float(np.count_nonzero(in_gt & in_pred) / union) if union else float("nan")
    return scores


def box_of_points(xy: np.ndarray) -> np.ndarray:
    """Axis-aligned ``[x, y, w, h]`` box around points :math:`(N, 2)`; NaNs when there are none."""
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ShapeError(f"points must be (N, 2), got {xy.shape}")
    if len(xy) == 0:
        return np.full(4, np.nan)
    low, high = xy.min(axis=0), xy.max(axis=0)
    return np.array([low[0], low[1], high[0] - low[0], high[1] - low[1]])


def box_intersection(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersection area of ``[x, y, w, h]`` boxes, broadcasting over leading dimensions."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    width = np.minimum(a[..., 0] + a[..., 2], b[..., 0] + b[..., 2]) - np.maximum(a[..., 0], b[..., 0])
    height = np.minimum(a[..., 1] + a[..., 3], b[..., 1] + b[..., 3]) - np.maximum(a[..., 1], b[..., 1])
    return np.clip(width, 0, None) * np.clip(height, 0, None)


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of ``[x, y, w, h]`` boxes, broadcasting; 0 where the union is empty or a box is NaN."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    inter = box_intersection(a, b)
    union = a[..., 2] * a[..., 3] + b[..., 2] * b[..., 3] - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(union > 0, inter / union, 0.0)
    return np.nan_to_num(iou, nan=0.0)


def boxes_nested(
    a: np.ndarray, b: np.ndarray, min_cover: float = 0.5, max_area_ratio: float = 4.0
) -> np.ndarray:
    """Whether ``[x, y, w, h]`` boxes nest, broadcasting over leading dimensions.

    Args:
        a, b: boxes :math:`(..., 4)`.
        min_cover: the intersection must cover more than this fraction of the smaller box's area.
        max_area_ratio: the larger area may be at most this multiple of the smaller.

    Returns:
        Bool :math:`(...)`; ``False`` where a box is empty or NaN.
    """
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    area_a, area_b = a[..., 2] * a[..., 3], b[..., 2] * b[..., 3]
    smaller, larger = np.minimum(area_a, area_b), np.maximum(area_a, area_b)
    covered = box_intersection(a, b) > min_cover * smaller
    return (smaller > 0) & covered & (larger <= max_area_ratio * smaller)


def convex_hull_mask(xy: np.ndarray, sensor_size: tuple[int, int]) -> np.ndarray:
    """Dense mask of the convex hull of points, :math:`(H, W)` bool (EMSGC's EV-IMO mask)."""
    height, width = sensor_size
    mask = np.zeros((height, width), dtype=np.uint8)
    xy = np.asarray(xy, dtype=np.float64)
    if len(xy) >= 1:
        hull = cv2.convexHull(np.rint(xy).astype(np.int32).reshape(-1, 1, 2))
        cv2.fillConvexPoly(mask, hull, 1)
    return mask.astype(bool)


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """IoU of two boolean masks of equal shape; NaN when both are empty."""
    a, b = np.asarray(a, dtype=bool), np.asarray(b, dtype=bool)
    if a.shape != b.shape:
        raise ShapeError(f"masks differ in shape: {a.shape} and {b.shape}")
    union = np.count_nonzero(a | b)
    return float(np.count_nonzero(a & b) / union) if union else float("nan")


def mean_iou(pred_dynamic: np.ndarray, gt_dynamic: np.ndarray) -> float:
    """mIoU of a binary dynamic/background labelling: the mean of the two classes' IoUs.

    Args:
        pred_dynamic, gt_dynamic: bool arrays of one shape (pixels :math:`(H, W)` or events :math:`(N,)`).

    Returns:
        ``(IoU(dynamic) + IoU(background)) / 2``; a class absent from both is left out of the mean (as
        ``nanmean`` in event_suppression); NaN when both arrays are empty.

    Examples:
        >>> mean_iou(np.array([1, 1, 0, 0], bool), np.array([1, 0, 0, 0], bool))  # (1/2 + 2/3) / 2
        0.5833333333333333
    """
    pred, gt = np.asarray(pred_dynamic, dtype=bool), np.asarray(gt_dynamic, dtype=bool)
    ious = [mask_iou(pred, gt), mask_iou(~pred, ~gt)]
    defined = [value for value in ious if not np.isnan(value)]
    return float(np.mean(defined)) if defined else float("nan")


def event_pixel_iou(pred_mask: np.ndarray, gt_mask: np.ndarray, event_mask: np.ndarray) -> float:
    """pIoU: the dynamic IoU counted only on the pixels that hold at least one event.

    Args:
        pred_mask, gt_mask: predicted and ground-truth dynamic masks, bool :math:`(H, W)`.
        event_mask: the pixels holding events, bool :math:`(H, W)`.

    Returns:
        ``mask_iou(pred_mask & event_mask, gt_mask & event_mask)``; NaN when both are empty.
    """
    event_mask = np.asarray(event_mask, dtype=bool)
    return mask_iou(
        np.asarray(pred_mask, dtype=bool) & event_mask, np.asarray(gt_mask, dtype=bool) & event_mask
    )


def success_rate(ious, threshold: float = 0.5) -> float:
    """SR@threshold: the fraction of frames whose IoU is at least ``threshold``, NaN frames left out.

    Returns:
        A fraction in [0, 1]; NaN when no frame has a defined IoU.

    Examples:
        >>> success_rate([0.7, 0.5, 0.2, float("nan")])
        0.6666666666666666
    """
    values = np.asarray(ious, dtype=np.float64)
    values = values[~np.isnan(values)]
    return float(np.mean(values >= threshold)) if len(values) else float("nan")


def event_iou(is_dynamic: np.ndarray, events: np.ndarray, gt_mask: np.ndarray) -> float:
    """Event IoU: the events predicted dynamic against the events on ground-truth object pixels.

    Args:
        is_dynamic: whether each event is predicted dynamic, bool :math:`(N,)`.
        events: canonical events :math:`(N,)` inside the mask.
        gt_mask: the ground-truth object mask, bool :math:`(H, W)`.

    Returns:
        ``|P ∩ G| / |P ∪ G|`` over events (an event counts once per event, not per pixel); NaN when no
        event is predicted dynamic and none lies on the object.
    """
    is_dynamic = np.asarray(is_dynamic, dtype=bool)
    if is_dynamic.shape != events.shape:
        raise ShapeError(
            f"is_dynamic must be (N,) like the events, got {is_dynamic.shape} for {events.shape}"
        )
    return mask_iou(is_dynamic, np.asarray(gt_mask, dtype=bool)[events["y"], events["x"]])


# Outcomes of :func:`object_outcomes`, the detected one first.
OUTCOMES = ("detected", "background", "merged", "split", "stretched", "unassigned")
# A holder with at least this many events of other objects per event of the object is "merged"; one with
# less than this share of the object's events is "split" (docs/objects.md).
_MERGED_SHARE, _SPLIT_SHARE = 0.3, 0.6


def object_outcomes(
    pred: np.ndarray, gt: np.ndarray, detected, dynamic: np.ndarray, ignore: int = -1
) -> tuple[str, ...]:
    """Each ground-truth object's outcome: ``"detected"``, or why it was missed (module docstring).

    A missed object's *holder* is the cluster with most of its events. It is ``"background"`` when most
    of the holder's events are predicted static; ``"merged"`` when the holder has at least 0.3 events of
    other objects per event of this one; ``"split"`` when it holds under 60 % of the object's events;
    ``"stretched"`` otherwise. ``"unassigned"``: none of the object's events has a cluster.

    Args:
        pred: predicted cluster of each event :math:`(N,)`; negative values are unassigned.
        gt: ground-truth layer of each event :math:`(N,)`: 0 the background, ``ignore`` left out.
        detected: whether each object is detected, one flag per layer above 0 of ``gt`` in increasing order.
        dynamic: whether each event is predicted dynamic (off the background), bool :math:`(N,)`.

    Returns:
        One of :data:`OUTCOMES` per object, in the order of ``detected``.
    """
    pred, gt = _labels(pred, gt)
    dynamic = np.asarray(dynamic, dtype=bool)
    objects = [int(v) for v in np.unique(gt) if v > 0 and v != ignore]
    if len(objects) != len(detected):
        raise ShapeError(f"detected has {len(detected)} flags for {len(objects)} objects")
    outcomes = []
    for layer, found in zip(objects, detected, strict=True):
        own = (gt == layer) & (pred >= 0)
        if found or not np.any(own):
            outcomes.append("detected" if found else "unassigned")
            continue
        holder = int(np.bincount(pred[own]).argmax())
        held = pred == holder
        foreign = np.count_nonzero(held & (gt > 0) & (gt != layer) & (gt != ignore))
        share = np.count_nonzero(held & own) / np.count_nonzero(gt == layer)
        if np.count_nonzero(dynamic[held]) * 2 < np.count_nonzero(held):
            outcomes.append("background")
        elif foreign >= _MERGED_SHARE * np.count_nonzero(held & own):
            outcomes.append("merged")
        elif share < _SPLIT_SHARE:
            outcomes.append("split")
        else:
            outcomes.append("stretched")
    return tuple(outcomes)


def _labels(pred, gt) -> tuple[np.ndarray, np.ndarray]:
    pred, gt = np.asarray(pred).astype(np.int64), np.asarray(gt).astype(np.int64)
    if pred.shape != gt.shape or pred.ndim != 1:
        raise ShapeError(f"pred and gt must be (N,) of equal length, got {pred.shape} and {gt.shape}")
    return pred, gt

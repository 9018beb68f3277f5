"""Where each cluster's fit runs: crops of the sensor around small clusters, and gathered events.

A cluster's image only needs the pixels its events reach, so small clusters are fitted in crops
(:func:`fit_crops`) and every cluster's events are gathered into rows of their own
(:func:`gather_members`): a fit then costs in proportion to its cluster, not to the window and sensor.
"""

from __future__ import annotations

import torch
from torch import Tensor

from evseg_torch.errors import ShapeError
from evseg_torch.events import EventBatch
from evseg_torch.level_two.image.warp import LinearWarp

__all__ = ["fit_crops", "gather_members"]

# Pixels a fit's crop reaches beyond its events' raw and initially warped positions: room for the
# warps of a fit to move (refits move models by a pixel or two) and for the blur.
_CROP_MARGIN = 8.0
# Clusters whose crops cover at most this fraction of the sensor are fitted in crops (see fit_crops).
_SMALL_CROP = 0.25


def fit_crops(
    warp: LinearWarp,
    weights: Tensor,
    params: Tensor,
    sensor_size: tuple[int, int],
    window: Tensor,
    cropped: bool = True,
) -> tuple[list[tuple[Tensor, tuple[int, int]]], Tensor]:
    """The fits of a call: each window's clusters in crops around them, and its other clusters.

    A cluster's image only needs the pixels its events reach: its box spans its events' raw and initially
    warped positions plus :data:`_CROP_MARGIN` pixels. A window's clusters whose boxes cover at most
    :data:`_SMALL_CROP` of the sensor are fitted together in crops of their largest box; its others in
    the whole sensor. Contrast then costs in proportion to the crops' area, not K sensors'. The variance
    objectives sum the squared image over the pixels the events reach, so the optimum is the same as
    over the whole sensor while the events stay inside their crop.

    Args:
        warp, weights: each cluster's gathered events and weights, :math:`(C, n)`.
        params: each cluster's initial parameters :math:`(C, P)`.
        sensor_size: ``(H, W)``.
        window: each cluster's window, int64 :math:`(C,)`.
        cropped: ``False`` fits every window's clusters together in the whole sensor.

    Returns:
        ``(fits, origin)``: each fit's cluster rows and crop ``(H, W)``, a window's crops first; and the
        top-left pixel of each cluster's crop :math:`(C, 2)` (0 on the whole sensor), to be subtracted
        from its positions.
    """
    height, width = sensor_size
    limit = torch.tensor([width - 1.0, height - 1.0], dtype=warp.xy.dtype, device=warp.xy.device)
    with torch.no_grad():
        member = (weights != 0)[..., None]
        reach = torch.cat([warp.xy, warp.warped(params)], dim=1)
        inside = torch.cat([member, member], dim=1)
        big = torch.finfo(reach.dtype).max
        low = torch.where(inside, reach, big).amin(dim=1).sub(_CROP_MARGIN).clamp(min=0).floor()
        high = torch.where(inside, reach, -big).amax(dim=1).add(_CROP_MARGIN).clamp(max=limit).ceil()
        extent = (high - low).clamp_min(0)
        small = (extent[:, 0] + 1) * (extent[:, 1] + 1) <= _SMALL_CROP * height * width
        keys, fit = torch.unique(2 * window + (~(small & cropped)).long(), return_inverse=True)
        span = extent.new_zeros(len(keys), 2).scatter_reduce(
            0, fit[:, None].expand(-1, 2), extent, "amax", include_self=False
        )
        span = torch.where((keys % 2 == 0)[:, None], span, limit)
        origin = torch.minimum(low, limit - span[fit])
    order = torch.argsort(fit, stable=True)
    counts = torch.bincount(fit, minlength=len(keys))
    sizes = torch.cat([span + 1, counts[:, None].to(span.dtype)], dim=1).long().tolist()
    rows = order.split([count for *_, count in sizes])
    return [(own, (h, w)) for own, (w, h, _) in zip(rows, sizes, strict=True)], origin


def gather_members(
    events: EventBatch, weights: Tensor, window: Tensor | None = None
) -> tuple[EventBatch, Tensor]:
    """Each cluster's events with non-zero weight, padded to the largest cluster with zero weights.

    Warping and splatting then cost one pass over the events in all, not one per cluster.

    Args:
        events: one window of N events, or a padded batch of windows :math:`(B, N_{max})`.
        weights: one row per cluster, :math:`(K, N)` (:math:`(K, N_{max})` for a batch).
        window: for a batch, each cluster's window, int64 :math:`(K,)`.

    Returns:
        The clusters' events ``xy`` :math:`(K, n, 2)`, ``t`` and ``p`` :math:`(K, n)`, in event order, and
        their weights :math:`(K, n)`, zero on the padding.
    """
    if events.is_batched:
        if window is None or window.shape != weights.shape[:1]:
            raise ShapeError(f"a batch needs each cluster's window (K,) = ({weights.shape[0]},)")
        fields = (events.xy, events.t, events.p)
    else:
        fields = (events.xy[None], events.t[None], events.p[None])
        window = torch.zeros(weights.shape[0], dtype=torch.long, device=weights.device)
    member = weights != 0
    rows, cols = member.nonzero(as_tuple=True)  # row-major: each cluster's members in their order
    counts = member.sum(dim=1)
    slots = torch.arange(rows.shape[0], device=rows.device) - (torch.cumsum(counts, 0) - counts)[rows]
    shape = (weights.shape[0], int(counts.max()) if len(counts) else 0)
    order = rows.new_zeros(shape).index_put_((rows, slots), cols)
    filled = torch.arange(shape[1], device=rows.device) < counts[:, None]
    padded = torch.where(filled, weights.gather(1, order), 0)
    source = window[:, None]
    return EventBatch(*(field[source, order] for field in fields)), padded

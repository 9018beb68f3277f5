r"""EMSGC's data term: how well each motion model compensates each event.

For every model :math:`l` of a pool (EMSGC ``computeDataTermLookUpTables_GMM_undistortion``):

1. warp **all** events of the window with :math:`\theta_l` and build the IWE :math:`I_l` (bilinear
   voting, Gaussian blur of width ``sigma``, :func:`~evseg_torch.level_two.image.splat.splat_events`);
2. normalise (below) and take the negative image, 0 at the sharpest value;
3. the cost of event :math:`k` under :math:`l` is that image read by bilinear interpolation at the
   event's warped position :math:`x'_k(\theta_l)`, or 255 where that position is outside the image.

Events that a model compensates well land on sharp, bright edges of its IWE and pay little; a fully
unexplained event pays 255. The costs stay in ``[0, 255]``, so EMSGC's ranges of ``lambda_smooth`` and
``lambda_label`` apply.

Normalisations (``normalization``):

* ``"global"`` (EMSGC): :math:`D_k(l) = 255 (1 - I_l(x'_k) / M)` with :math:`M = \max_{l, x} I_l(x)`. One
  bright peak anywhere (a dense, well-focused object) pushes every other event's costs towards 255 and
  squeezes the differences between models, so the Potts term then decides alone.
* ``"relative"`` (level two's; a deviation from EMSGC): each event's values are divided by its own best
  value over the pool, floored: :math:`D_k(l) = 255 (1 - \min(1, I_l(x'_k) / \max(\max_m I_m(x'_m),
  F_k)))`. An event's best model costs 0 and the others pay in proportion to how much less sharply they
  compensate it; events that every model compensates alike (the aperture problem) cost about the same
  under all, and the Potts term labels them by their neighbours. The floor :math:`F_k` is the larger of
  the ``floor_quantile`` of the best values of the events whose best model is event :math:`k`'s (each
  layer's events are scaled by that layer's own sharpness, so a sparse layer is not measured against
  a dense one's) and the ``pool_floor_quantile`` of all in-image values of the pool (noise and weak
  texture, whose values are all small, get no large differences out of small absolute ones).

Two refinements of EMSGC's construction (level two uses both):

* ``polarity``: one IWE per polarity and model, each event read from its own polarity's image: a wrong
  model that carries an event onto another layer's edge usually lands it on events of the other sign.
* ``margin``: the IWEs extend beyond the sensor, so that an event that its model carries out of the
  sensor's rectangle (texture entering the view during the window) still lands on its layer's image
  instead of costing 255 under its own, correct model. ``None`` takes the largest overshoot of any
  warped event, rounded up and capped at an eighth of the larger sensor side, so spurious fast models
  cannot inflate the images.

The defaults are level two's (:class:`~evseg_torch.config.LevelTwoConfig`'s ``data_*`` settings);
``sigma=1.0, normalization="global", polarity=False, margin=0`` is EMSGC's data term.

Pixel convention: pixel centres sit at integer coordinates, in the splatting and in the lookup alike, so
an event that votes all its weight into one pixel reads that pixel back (EMSGC reads half a pixel off).
"Outside" means outside the closed rectangle :math:`[0, W - 1] \times [0, H - 1]` of pixel centres. No
rounding to integers (EMSGC rounds for GCO's integer energies): the graph cut works in float64.

On the CPU, the per-polarity ``"relative"`` costs run as compiled loops where
:mod:`evseg_torch.backend` chooses them (:mod:`~evseg_torch.kernels.data_term`), the same costs bit for
bit; with a gradient to keep, the tensor code runs. Measurements:
``docs/notes/2026-12-04-data-term-floor.md``, ``docs/notes/2026-12-04-sharper-data-term.md``,
``docs/notes/2026-12-07-level-two-rationale.md``.
"""

from __future__ import annotations

import math
from numbers import Real

import numpy as np
import torch
from torch import Tensor, nn

from evseg_torch.backend import kernel
from evseg_torch.config import LevelTwoConfig
from evseg_torch.errors import ConfigError, ModelError, ShapeError
from evseg_torch.events import EventBatch, batch_of_one
from evseg_torch.level_two.image.splat import extent_mask, read_flat, splat_events
from evseg_torch.level_two.image.warp import warp_events
from evseg_torch.motion import MotionModel
from evseg_torch.validation import check_integer

__all__ = ["DataCost", "data_cost", "sample_bilinear"]

MAX_COST = 255.0

NORMALIZATIONS = ("global", "relative")
"""Normalisations of the data term (module docstring)."""


def sample_bilinear(
    images: Tensor, xy: Tensor, image_index: Tensor | None = None, extent: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    r"""Read images by bilinear interpolation at sub-pixel positions (pixel centres at integers).

    Args:
        images: :math:`(M, H, W)`.
        xy: positions :math:`(K, N, 2)`, ``x`` the column and ``y`` the row.
        image_index: which image each position reads, int64 :math:`(K, N)` in ``[0, M)``; by default
            row ``k`` of ``xy`` reads image ``k`` (then ``M`` must equal ``K``).
        extent: optional int64 ``(height, width)`` of the image each position reads, broadcast against
            ``xy``, e.g. :math:`(K, 1, 2)`: images of different sizes in the top-left corners of one
            canvas (see :func:`~evseg_torch.level_two.image.splat.splat_events`); a position is read as if its
            image were only that large.

    Returns:
        ``(values, inside)``, both :math:`(K, N)`: the interpolated values (0 where outside) and whether
        the position lies in :math:`[0, W - 1] \times [0, H - 1]` (of its extent, when given).

    Examples:
        >>> image = torch.arange(6.0).view(1, 2, 3)
        >>> sample_bilinear(image, torch.tensor([[[0.5, 0.5], [3.0, 0.0]]]))
        (tensor([[2., 0.]]), tensor([[ True, False]]))
    """
    if (
        images.ndim != 3
        or xy.ndim != 3
        or xy.shape[-1] != 2
        or (image_index is None and xy.shape[0] != images.shape[0])
        or (image_index is not None and image_index.shape != xy.shape[:2])
    ):
        raise ShapeError(
            f"images must be (M, H, W), xy (K, N, 2) and image_index (K, N) or None for M = K, got "
            f"{tuple(images.shape)}, {tuple(xy.shape)} and "
            f"{None if image_index is None else tuple(image_index.shape)}"
        )
    height, width = images.shape[-2:]
    x, y = xy[..., 0], xy[..., 1]
    # The top-left tap stays one pixel inside the last row and column (of the extent), where fx or fy is 1.
    if extent is None:
        last_row, last_col = height - 1, width - 1
        top_row, top_col = max(height - 2, 0), max(width - 2, 0)
    else:
        last_row, last_col = (extent[..., axis].to(xy.dtype) - 1 for axis in (0, 1))
        top_row, top_col = (last_row - 1).clamp(min=0), (last_col - 1).clamp(min=0)
    inside = (x >= 0) & (x <= last_col) & (y >= 0) & (y <= last_row)
    col = x.detach().floor().clamp(min=0).clamp(max=top_col)
    row = y.detach().floor().clamp(min=0).clamp(max=top_row)
    fx, fy = (x - col).clamp(0, 1), (y - row).clamp(0, 1)
    if image_index is None:
        image_index = torch.arange(xy.shape[0], device=xy.device)[:, None]
    flat = images.reshape(-1)
    base = image_index * (height * width) + row.long() * width + col.long()
    right = min(1, width - 1)
    down = width if height > 1 else 0

    def tap(offset: int) -> Tensor:
        return read_flat(flat, base + offset)

    top = tap(0) * (1 - fx) + tap(right) * fx
    bottom = tap(down) * (1 - fx) + tap(down + right) * fx
    values = top * (1 - fy) + bottom * fy
    return values * inside, inside


def data_cost(
    model: MotionModel,
    events: EventBatch,
    params: Tensor,
    sensor_size: tuple[int, int] | None = None,
    sigma: float = LevelTwoConfig.data_sigma,
    normalization: str = LevelTwoConfig.data_normalization,
    polarity: bool = LevelTwoConfig.data_polarity,
    margin: int | None = None,
    valid: Tensor | None = None,
    floor_quantile: float | None = LevelTwoConfig.data_floor_quantile,
    pool_floor_quantile: float | None = LevelTwoConfig.data_pool_floor_quantile,
) -> Tensor:
    r"""EMSGC's per-event data cost under each model of a pool, batched over the models and windows.

    .. math::

        D_k(l) = 255 \Big(1 - \frac{I_l(x'_k(\theta_l))}{M_k}\Big), \qquad
        D_k(l) = 255 \text{ where } x'_k(\theta_l) \text{ is outside the image,}

    with :math:`M_k = \max_{m, x} I_m(x)` (``"global"``, EMSGC) or the event's own best value, floored
    (``"relative"``, see the module docstring).

    A padded batch of windows is one computation: every window's IWEs come from one splat and one blur,
    normalised per window, so each window's costs equal those of the window alone. Windows whose margins
    (``margin=None``) differ share a canvas of the widest, each image confined to its own extent.

    Args:
        model: the motion model.
        events: one window, ``xy`` :math:`(N, 2)` and ``t`` :math:`(N,)` relative to the reference
            time; or a padded batch of B windows (:func:`~evseg_torch.events.batch_windows`).
        params: the pool, :math:`(K, P)`; for a batch one pool per window, :math:`(B, K, P)`, padded to
            the largest pool (see ``valid``).
        sensor_size: ``(H, W)``; defaults to ``model.sensor_size``.
        sigma: Gaussian blur of the IWEs in pixels (EMSGC: 1; keep it so that EMSGC's λ values apply).
        normalization: ``"global"`` (EMSGC) or ``"relative"``.
        polarity: read each event from the IWE of its own polarity's events (EMSGC: one IWE of all).
        margin: pixels the IWEs extend beyond the sensor on every side (EMSGC: 0); ``None`` chooses, per
            window, the smallest margin that holds every warped event, capped at ``max(H, W) / 8`` (see
            the module docstring).
        valid: for a batch, bool :math:`(B, K)`, which models of each pool are real; ``None`` for all.
            The others take no part in the normalisation or the margin and cost 255 at every event, so
            they never win.
        floor_quantile: in ``"relative"`` normalisation, the quantile, in ``(0, 1]``, of the best values
            of the events whose best model is an event's own that floors its best value; ``None`` for
            no such floor.
        pool_floor_quantile: in ``"relative"`` normalisation, the quantile, in ``(0, 1]``, of all
            in-image values of the pool that floors every event's best value; ``None`` for none.

    Returns:
        Costs in ``[0, 255]``, :math:`(N, K)`, or :math:`(B, N_{max}, K)` for a batch (255 at padding
        events and models), in the dtype and on the device of ``events``; differentiable with respect to
        ``params`` (almost everywhere).

    Raises:
        ShapeError: if ``params`` is not :math:`(K, P)` (:math:`(B, K, P)` for a batch) with ``K >= 1``
            and the model's ``P``, or ``valid`` is not :math:`(B, K)`.
        ModelError: if ``params`` hold NaN or inf.
        ConfigError: for an unknown ``normalization``, or a floor quantile that is not ``None`` or in
            ``(0, 1]``.

    Examples:
        >>> from evseg_torch.events import batch_windows
        >>> from evseg_torch.motion import Translation
        >>> events = EventBatch(torch.rand(100, 2) * 15, torch.rand(100) * 0.01, torch.ones(100))
        >>> data_cost(Translation((16, 16)), events, torch.zeros(3, 2)).shape
        torch.Size([100, 3])
        >>> fewer = EventBatch(events.xy[:60], events.t[:60], events.p[:60])
        >>> data_cost(Translation((16, 16)), batch_windows([events, fewer]), torch.zeros(2, 3, 2)).shape
        torch.Size([2, 100, 3])
    """
    batched = events.is_batched
    expected = (len(events),) if batched else ()
    if (
        params.shape[:-2] != expected
        or params.ndim != len(expected) + 2
        or params.shape[-2] == 0
        or params.shape[-1] != model.n_params
    ):
        shape = f"(B, K, {model.n_params})" if batched else f"(K, {model.n_params})"
        raise ShapeError(
            f"params must be {shape} with K >= 1 for the {model.name} model"
            + (f" and B = {len(events)} windows" if batched else "")
            + f", got {tuple(params.shape)}"
        )
    if valid is not None and (not batched or valid.shape != params.shape[:2]):
        raise ShapeError(
            f"valid must be (B, K) = {tuple(params.shape[:-1])} for a batch, got {tuple(valid.shape)}"
        )
    if not torch.isfinite(params).all():
        raise ModelError("params hold NaN or inf: every model's parameters must be finite")
    if normalization not in NORMALIZATIONS:
        raise ConfigError(f"normalization must be one of {NORMALIZATIONS}, got {normalization!r}")
    _check_margin(margin)
    _check_floor_quantiles(floor_quantile, pool_floor_quantile)
    if not batched:
        events, params = batch_of_one(events), params[None]
    n_windows, n_models = params.shape[:2]
    height, width = sensor_size or model.sensor_size
    real = events.mask[:, None]  # (B, 1, N)
    if valid is not None:
        real = real & valid[..., None]
    warped = warp_events(model, events.xy[:, None], events.t[:, None], params)  # (B, K, N, 2)
    # Per-polarity "relative" costs on the CPU (level two's data term) come from compiled steps where
    # Numba is installed (data_term_kernel): the same margins, values and costs bit for bit.
    compiled = (
        polarity
        and normalization == "relative"
        and warped.device.type == "cpu"
        and warped.dtype == torch.float32
        and not (torch.is_grad_enabled() and warped.requires_grad)
        and kernel("data_term.polarity_values") is not None
    )
    if margin is not None:
        margins = [margin] * n_windows
    else:
        overshoots = kernel("data_term.overshoots") if compiled else _overshoots
        margins = _margins(overshoots(warped, real, height, width).tolist(), height, width)
    widest = max(margins)
    if widest:
        warped = warped + warped.new_tensor(margins)[:, None, None, None]
    size = (height + 2 * widest, width + 2 * widest)
    extent = None
    if min(margins) != widest:
        extent = torch.tensor([[height + 2 * m, width + 2 * m] for m in margins], device=warped.device)
        extent = extent[:, None]  # (B, 1, 2): the same image size for a window's models
    read_extent = None if extent is None else extent.expand(-1, n_models, -1).reshape(-1, 1, 2)
    votes = events.mask[:, None].to(warped.dtype)  # padding votes nothing
    if compiled and min(size) > 1:
        # The same values, flags and costs as the tensor code below, in one compiled pass per model.
        sizes = np.array(size) if extent is None else extent[:, 0].cpu().numpy()
        values, inside = kernel("data_term.polarity_values")(
            warped, events.p <= 0, votes[:, 0], np.broadcast_to(sizes, (n_windows, 2)), sigma
        )
        costs = kernel("data_term.relative_costs")
        cost = costs(values, inside, real, floor_quantile, pool_floor_quantile)
        return cost if batched else cost[0]
    if polarity:
        # (B, K, 2, H, W); image 2 (b K + k) reads window b's model k's positive events, the next its others.
        iwes = splat_events(warped, size, votes, sigma, polarity=events.p[:, None], extent=extent)
        own = 2 * torch.arange(n_windows * n_models, device=params.device).view(n_windows, n_models, 1)
        own = own + (events.p <= 0)[:, None].long()
        values, inside = sample_bilinear(
            iwes.flatten(0, 2), warped.flatten(0, 1), own.flatten(0, 1), read_extent
        )
    else:
        iwes = splat_events(warped, size, votes, sigma, extent=extent)  # (B, K, H, W)
        values, inside = sample_bilinear(iwes.flatten(0, 1), warped.flatten(0, 1), extent=read_extent)
    inside = inside.view_as(real.expand(n_windows, n_models, -1)) & real
    values = values.view_as(inside) * inside
    tiny = torch.finfo(values.dtype).tiny
    if normalization == "global":
        shown = iwes
        if extent is not None:
            shown = shown * extent_mask(extent, size).view(n_windows, *[1] * (iwes.ndim - 3), *size)
        if valid is not None:
            shown = shown * valid.view(*valid.shape, *[1] * (iwes.ndim - 2))
        peak = shown.flatten(1).amax(dim=1).clamp_min(tiny)[:, None, None]
    else:
        best, owner = values.max(dim=1)  # (B, N): each event's best value and the model giving it
        floor = torch.full_like(best, tiny)
        if pool_floor_quantile is not None:
            floor = floor.maximum(_quantile(values, inside, pool_floor_quantile)[:, None])
        if floor_quantile is not None:
            floor = floor.maximum(_own_floors(best, owner, inside.any(dim=1), n_models, floor_quantile))
        peak = best.maximum(floor)[:, None]
    ratio = (values / peak).clamp(max=1)
    cost = torch.where(inside, MAX_COST * (1 - ratio), torch.full_like(values, MAX_COST)).transpose(1, 2)
    return cost if batched else cost[0]


def _check_margin(margin) -> None:
    if margin is not None:
        check_integer(margin, "margin")


def _check_floor_quantiles(own, pool) -> None:
    for name, quantile in (("floor_quantile", own), ("pool_floor_quantile", pool)):
        if quantile is not None and (
            isinstance(quantile, bool) or not isinstance(quantile, Real) or not 0 < quantile <= 1
        ):
            raise ConfigError(f"{name} must be None or a number in (0, 1], got {quantile!r}")


def _own_floors(best: Tensor, owner: Tensor, seen: Tensor, n_models: int, q: float) -> Tensor:
    """Each event's own floor: the ``q``-quantile of the best values of its window's events whose best
    model is its own.

    Args:
        best, owner: each event's best value and the model giving it, :math:`(B, N)`.
        seen: whether the event is inside the image of some model, :math:`(B, N)`.

    Returns:
        :math:`(B, N)`.
    """
    n_windows, n_events = best.shape
    models = torch.arange(n_models, device=owner.device)[:, None]
    mine = (owner[:, None] == models) & seen[:, None]  # (B, K, N)
    values = best[:, None].expand(-1, n_models, -1).reshape(n_windows * n_models, n_events)
    floors = _quantile(values, mine.flatten(0, 1), q).view(n_windows, n_models)
    return floors.gather(1, owner)


def _overshoots(warped: Tensor, real: Tensor, height: int, width: int) -> Tensor:
    """Per window, the largest overshoot of a real warped position :math:`(B, K, N, 2)` beyond the
    sensor's pixel centres, :math:`(B,)` (``-inf`` where none is real)."""
    limit = warped.new_tensor([width - 1, height - 1])
    overshoot = torch.maximum(-warped, warped - limit).amax(dim=-1)
    return torch.where(real, overshoot, -torch.inf).flatten(1).amax(dim=1)


def _margins(overshoots: list[float], height: int, width: int) -> list[int]:
    """The smallest whole margin holding each window's overshoot, capped at an eighth of the larger side."""
    cap = math.ceil(max(height, width) / 8)
    return [min(math.ceil(max(value, 0.0)), cap) for value in overshoots]


def _quantile(values: Tensor, selected: Tensor, q: float) -> Tensor:
    """Per window, the ``q``-quantile of its selected values, by selection and without interpolation (no
    size limit, unlike ``torch.quantile``); the smallest normal number where none is selected.

    On the CPU each window's selected values alone go through NumPy's introselect (``partition``); an own
    floor selects each model's events out of all of the window's, so selecting from the whole rows cost
    as many passes as models. Elsewhere one ``kthvalue`` serves every window (below). Both pick the same
    element.

    Args:
        values, selected: :math:`(B, ...)`.

    Returns:
        :math:`(B,)`.
    """
    counts = selected.flatten(1).sum(dim=1)
    ranks = (counts.double() * q).round().clamp_min(1).long()
    select = _select_by_partition if values.device.type == "cpu" else _select_by_kthvalue
    return select(values.detach().flatten(1), selected.flatten(1), ranks, counts)


def _select_by_partition(values: Tensor, selected: Tensor, ranks: Tensor, counts: Tensor) -> Tensor:
    """Each row's ``ranks``-th smallest selected value (CPU tensors :math:`(B, M)`), by NumPy."""
    tiny = torch.finfo(values.dtype).tiny
    rows, chosen = values.numpy(), selected.numpy()
    kth = [
        np.partition(row[mask], rank - 1)[rank - 1] if count else tiny
        for row, mask, rank, count in zip(rows, chosen, ranks.tolist(), counts.tolist(), strict=True)
    ]
    return torch.tensor(np.array(kth, dtype=rows.dtype))


def _select_by_kthvalue(values: Tensor, selected: Tensor, ranks: Tensor, counts: Tensor) -> Tensor:
    """Each row's ``ranks``-th smallest selected value :math:`(B, M)`, by one ``kthvalue`` for all rows."""
    flat = torch.where(selected, values, torch.inf)
    # Each window's rank becomes the largest by as many -inf beside its values: one kthvalue for all. The
    # padding is only as wide as that (none for one window) and the top rank needs.
    top = int(ranks.max())
    width = max(top - int(ranks.min()), top - flat.shape[1])
    if width:
        lead = torch.arange(width, device=flat.device) < (top - ranks)[:, None]
        flat = torch.cat([flat, torch.where(lead, -torch.inf, torch.inf).to(flat.dtype)], dim=1)
    kth = flat.kthvalue(top, dim=1).values
    return torch.where(counts > 0, kth, torch.finfo(values.dtype).tiny)


class DataCost(nn.Module):
    r"""Module form of :func:`data_cost`.

    Args:
        model: the motion model.
        sensor_size: ``(H, W)``; defaults to ``model.sensor_size``.
        sigma: Gaussian blur of the IWEs in pixels.
        normalization: ``"global"`` (EMSGC) or ``"relative"``.
        polarity: read each event from its own polarity's IWE.
        margin: IWE margin in pixels beyond the sensor; ``None`` chooses it per call and window.
        floor_quantile, pool_floor_quantile: the floors' quantiles in ``"relative"`` normalisation.

    Shape:
        - Input: ``events`` of N events, ``params`` :math:`(K, P)`; or a padded batch of B windows,
          ``params`` :math:`(B, K, P)` and optional ``valid`` :math:`(B, K)`.
        - Output: :math:`(N, K)`, or :math:`(B, N_{max}, K)`.
    """

    def __init__(
        self,
        model: MotionModel,
        sensor_size: tuple[int, int] | None = None,
        sigma: float = LevelTwoConfig.data_sigma,
        normalization: str = LevelTwoConfig.data_normalization,
        polarity: bool = LevelTwoConfig.data_polarity,
        margin: int | None = None,
        floor_quantile: float | None = LevelTwoConfig.data_floor_quantile,
        pool_floor_quantile: float | None = LevelTwoConfig.data_pool_floor_quantile,
    ) -> None:
        super().__init__()
        if normalization not in NORMALIZATIONS:
            raise ConfigError(f"normalization must be one of {NORMALIZATIONS}, got {normalization!r}")
        _check_margin(margin)
        _check_floor_quantiles(floor_quantile, pool_floor_quantile)
        self.model = model
        self.sensor_size = tuple(sensor_size or model.sensor_size)
        self.sigma = float(sigma)
        self.normalization = normalization
        self.polarity = bool(polarity)
        self.margin = margin
        self.floor_quantile = floor_quantile
        self.pool_floor_quantile = pool_floor_quantile

    def forward(self, events: EventBatch, params: Tensor, valid: Tensor | None = None) -> Tensor:
        return data_cost(
            self.model,
            events,
            params,
            self.sensor_size,
            self.sigma,
            self.normalization,
            polarity=self.polarity,
            margin=self.margin,
            valid=valid,
            floor_quantile=self.floor_quantile,
            pool_floor_quantile=self.pool_floor_quantile,
        )

    def extra_repr(self) -> str:
        return (
            f"model={self.model.name}, sensor_size={self.sensor_size}, sigma={self.sigma}, "
            f"normalization={self.normalization!r}, polarity={self.polarity}, margin={self.margin}, "
            f"floor_quantile={self.floor_quantile}, pool_floor_quantile={self.pool_floor_quantile}"
        )

r"""Contrast objectives of images of warped events, and contrast maximisation (CMax) per cluster.

**Losses are minimised**: every loss here is the *negative* contrast, so a sharper image of warped
events gives a lower loss.

Objectives (:data:`CONTRAST_OBJECTIVES`) map an IWE :math:`(..., H, W)` and a reference IWE (the same
events, unwarped) to a contrast :math:`(...)`:

* ``"variance"``: the variance of the image over all pixels (EMSGC, Gallego et al. 2018);
* ``"normalized_variance"``: that variance divided by the reference's (Stoffregen et al. 2020), so
  contrasts of clusters of different sizes are comparable.

**Event collapse.** Warps that can contract (the 4-DOF similarity's divergence, rotation's
perspective terms) raise the variance just by packing the same events into less area, so plain CMax
is biased towards contraction and can collapse the events onto a few pixels (Shiba et al., Sensors
2022). The guard is model-agnostic: each event's vote is weighted by the area element
``a_k = det(dx'/dx)`` of the warp at that event, raised to the power ``collapse_weight`` (γ). Shrinking
a set of thin edges by an area factor ``a`` multiplies the energy of their image by ``a^(-1/2)``, a
dense texture's by ``a^(-1)``; weights ``a^γ`` scale it by ``a^(2γ)``, so γ = 1/4 neutralises edges
and γ = 1/2 dense texture. The default 3/8 lies between; on synthetic edge scenes with 4-DOF motion it
cuts the contraction bias of the plain objective from 10% of the displacement (or total collapse on
dense texture) to 1–4%. Under a total collapse (``a -> 0``) the weights vanish, so collapse never
pays. Translations have ``a = 1`` and are unaffected. A penalty on the spread of the warped events
would misfire on legitimate fits: warping a small object that moved far within the window shrinks its
streak to a spot; the area element compares each event's neighbourhood at one time, so it measures
contraction and not motion blur.
"""

from __future__ import annotations

import itertools
import queue
import threading
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from evseg_torch.config import LevelTwoConfig
from evseg_torch.errors import ConfigError, ModelError, ShapeError
from evseg_torch.events import EventBatch
from evseg_torch.level_two.iwe import (
    _batch_of_one,
    _check_points,
    _check_sensor_size,
    extent_mask,
    splat_events,
)
from evseg_torch.motion import MotionModel

DEFAULT_COLLAPSE_WEIGHT = LevelTwoConfig.collapse_weight
"""Default exponent γ of the area-element weights of the event-collapse guard (module docstring); the
refits' setting ``collapse_weight`` of :class:`~evseg_torch.config.LevelTwoConfig`."""

OPTIMIZERS = ("lbfgs", "adam")
"""The refits' optimisers (:class:`ContrastMaximization`)."""

_MIN_AREA = 1e-6  # folded warps (a <= 0) keep a tiny weight and a finite gradient
# Pixels a fit's crop reaches beyond its events' raw and initially warped positions: room for the
# warps of a fit to move (refits move models by a pixel or two) and for the blur.
_CROP_MARGIN = 8.0
# Clusters whose crops cover at most this fraction of the sensor are fitted in crops (see _crops).
_SMALL_CROP = 0.25
# Values per block of _sum_ignoring_padding: long enough for torch's fast sums, short enough that the
# zeros completing the last block cost little.
_SUM_BLOCK = 256


def image_variance(iwe: Tensor, reference: Tensor | None = None, mask: Tensor | None = None) -> Tensor:
    r"""Variance of an image over its pixels, :math:`\frac{1}{|\Omega|}\sum_x (H(x) - \bar H)^2`.

    Args:
        iwe: :math:`(..., H, W)`.
        reference: unused; accepted so that every objective in :data:`CONTRAST_OBJECTIVES` is called alike.
        mask: optional bool :math:`(..., H, W)`, broadcastable: :math:`\Omega`, the pixels of each image
            (images of different sizes in one canvas, see
            :func:`~evseg_torch.level_two.iwe.extent_mask`); ``None`` for all.

    Returns:
        :math:`(...)`.

    Examples:
        >>> image_variance(torch.rand(3, 8, 8)).shape
        torch.Size([3])
        >>> image = torch.tensor([[1.0, 3.0, 7.0]])
        >>> image_variance(image, mask=torch.tensor([[True, True, False]]))
        tensor(1.)
    """
    _check_image(iwe, "iwe")
    if mask is None:
        flat = iwe.flatten(-2)
        # Written out: torch.var's forward and backward take twice as long on CPU.
        return (flat - flat.mean(dim=-1, keepdim=True)).square().mean(dim=-1)
    # Sums that the zeros beyond an image's pixels do not change: an image has the same variance and
    # gradient, bit for bit, alone and in any larger canvas. The mean is detached: the deviations sum to
    # zero, so no gradient flows through it, and autograd's rounded sum of them would depend on the canvas.
    count = mask.sum(dim=(-2, -1))
    mean = _sum_ignoring_padding(_sum_ignoring_padding(torch.where(mask, iwe, 0))) / count
    deviation = torch.where(mask, iwe - mean.detach()[..., None, None], 0)
    return _sum_ignoring_padding(_sum_ignoring_padding(deviation.square())) / count


def normalized_variance(iwe: Tensor, reference: Tensor, mask: Tensor | None = None) -> Tensor:
    r"""Variance of ``iwe`` relative to that of ``reference``, Stoffregen et al.'s flow warp loss.

    Args:
        iwe: :math:`(..., H, W)`, the image of warped events.
        reference: :math:`(..., H, W)`, broadcastable, normally the image of the same events unwarped.
        mask: optional bool :math:`(..., H, W)`, the pixels of each image (see :func:`image_variance`).

    Returns:
        :math:`(...)`; 1 means no sharper than the reference. An empty reference gives NaN.

    Examples:
        >>> normalized_variance(torch.rand(3, 8, 8), torch.rand(8, 8)).shape
        torch.Size([3])
    """
    _check_image(reference, "reference")
    return image_variance(iwe, mask=mask) / image_variance(reference, mask=mask)


CONTRAST_OBJECTIVES: dict[str, Callable[..., Tensor]] = {
    "variance": image_variance,
    "normalized_variance": normalized_variance,
}
"""Contrast objectives by name; each maps ``(iwe, reference)`` to a contrast to be maximised, and takes a
``mask`` keyword, the pixels of each image, when images of different sizes share one canvas."""

_USES_REFERENCE = frozenset({"normalized_variance"})


def contrast_loss(
    model: MotionModel,
    events: EventBatch,
    params: Tensor,
    weights: Tensor | None = None,
    *,
    sensor_size: tuple[int, int] | None = None,
    objective: str = "variance",
    sigma: float = 1.0,
    collapse_weight: float = DEFAULT_COLLAPSE_WEIGHT,
    reference: Tensor | None = None,
) -> Tensor:
    r"""Per-cluster negative contrast of the image of each cluster's own warped events.

    Cluster ``k``'s events are all events weighted by ``weights[k]`` (hard 0/1 labels or soft
    memberships), warped with ``params[k]``; with the collapse guard (module docstring) each vote is
    further weighted by the warp's area element to the power ``collapse_weight``.

    Args:
        model: the motion model.
        events: ``xy`` :math:`(N, 2)` and ``t`` :math:`(N,)` shared by every cluster, or each cluster's
            own (padded) events ``xy`` :math:`(K, N, 2)` and ``t`` :math:`(K, N)`.
        params: :math:`(K, P)` in the model's units.
        weights: :math:`(K, N)` or :math:`(N,)`; ``None`` means every event counts once in every cluster.
        sensor_size: ``(H, W)``; defaults to ``model.sensor_size``.
        objective: a key of :data:`CONTRAST_OBJECTIVES`.
        sigma: Gaussian blur of the IWEs in pixels (EMSGC: 1).
        collapse_weight: exponent γ of the event-collapse guard's area weights; 0 switches the guard
            off, leaving EMSGC's plain objective.
        reference: the reference IWEs for ``"normalized_variance"`` if already computed (they do not
            depend on ``params``), :math:`(K, H, W)` or :math:`(H, W)`; computed when ``None``.

    Returns:
        :math:`(K,)`, differentiable with respect to ``params``, ``weights`` and ``events.xy``.

    Raises:
        ConfigError: for an unknown objective or a negative ``collapse_weight``.
        ShapeError: if the shapes do not fit together.

    Examples:
        >>> from evseg_torch.motion import Affine4
        >>> events = EventBatch(torch.rand(50, 2) * 7, torch.rand(50) * 0.01, torch.ones(50))
        >>> contrast_loss(Affine4((8, 8)), events, torch.zeros(3, 4)).shape
        torch.Size([3])
    """
    contrast_fn = _objective(objective)
    if not collapse_weight >= 0:
        raise ConfigError(f"collapse_weight must be >= 0, got {collapse_weight}")
    sensor_size = sensor_size or model.sensor_size
    if params.ndim != 2:
        raise ShapeError(f"params must be (K, P), got {tuple(params.shape)}")
    if weights is not None and weights.shape[-1:] != events.xy.shape[-2:-1]:
        raise ShapeError(
            f"weights must be (K, N) or (N,) with N = {events.xy.shape[-2]}, got {tuple(weights.shape)}"
        )
    if objective in _USES_REFERENCE and reference is None:
        reference = splat_events(events.xy, sensor_size, weights, sigma)
    warp = _LinearWarp.build(model, events, with_area=collapse_weight > 0)
    return _contrast_loss(warp, params, weights, sensor_size, contrast_fn, sigma, collapse_weight, reference)


class _LinearWarp(NamedTuple):
    """The warp of fixed events as a linear map of the parameters (``v = J(x) params``): built once,
    it turns every evaluation of an optimiser into a few multiply-adds.

    ``operator`` is ``t J(x)`` and ``step_x``, ``step_y`` are ``t (J(x + e) - J(x))`` for one-pixel steps
    ``e`` (for the area element), all stored parameter-first, :math:`(P, ..., N, 2)`.
    """

    xy: Tensor
    operator: Tensor
    step_x: Tensor | None
    step_y: Tensor | None

    @classmethod
    def build(cls, model: MotionModel, events: EventBatch, with_area: bool = True) -> _LinearWarp:
        _check_points(events.xy, "events.xy")
        if events.t.shape != events.xy.shape[:-1]:
            raise ShapeError(
                f"events.t must have shape {tuple(events.xy.shape[:-1])} to match events.xy, "
                f"got {tuple(events.t.shape)}"
            )
        t = events.t[..., None, None]
        jacobian = model.jacobian(events.xy)
        operator = _parameter_first(t * jacobian)
        if not with_area:
            return cls(events.xy, operator, None, None)
        unit = torch.eye(2, dtype=events.xy.dtype, device=events.xy.device)
        step_x, step_y = (_parameter_first(t * (model.jacobian(events.xy + e) - jacobian)) for e in unit)
        return cls(events.xy, operator, step_x, step_y)

    def warped(self, params: Tensor) -> Tensor:
        return self.xy - _apply(self.operator, params)

    def rows(self, index: Tensor) -> _LinearWarp:
        """The warp of some clusters of a gathered :math:`(K, N, 2)` warp: rows ``index``."""
        steps = (None if step is None else step[:, index] for step in (self.step_x, self.step_y))
        return _LinearWarp(self.xy[index], self.operator[:, index], *steps)

    def area(self, params: Tensor) -> Tensor:
        dx, dy = _apply(self.step_x, params), _apply(self.step_y, params)
        return (1 - dx[..., 0]) * (1 - dy[..., 1]) - dx[..., 1] * dy[..., 0]


def _apply(operator: Tensor, params: Tensor) -> Tensor:
    """Per-event ``operator @ params``: :math:`(P, ..., N, 2)`, :math:`(..., P)` -> :math:`(..., N, 2)`."""
    if params.ndim == 0 or params.shape[-1] != operator.shape[0]:
        raise ShapeError(f"params must be (..., {operator.shape[0]}), got {tuple(params.shape)}")
    return _LinearMap.apply(operator, params)


class _LinearMap(torch.autograd.Function):
    """:func:`_apply` with a backward pass that sums each parameter's gradient over the events by
    :func:`_sum_ignoring_padding`: the gradient of a cluster padded with zero-weight events (to the
    largest cluster of a batch) is then the same, bit for bit, as without the padding, and a window's
    fits in a batch take exactly the steps they take alone (autograd's sums round differently for
    different lengths, and the fits' L-BFGS steps amplify that)."""

    @staticmethod
    def forward(ctx, operator: Tensor, params: Tensor) -> Tensor:
        ctx.save_for_backward(operator, params)
        # A sum over the few parameters of contiguous slices: 3x faster than matmul/einsum, which run
        # one tiny product per event or per cluster.
        product = operator[0] * params[..., 0, None, None]
        for index in range(1, operator.shape[0]):
            product = torch.addcmul(product, operator[index], params[..., index, None, None])
        return product

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, Tensor | None]:
        operator, params = ctx.saved_tensors
        shape, n_params, lead = operator.shape, operator.shape[0], grad.shape[:-2]
        # Both inputs viewed with all of the product's leading dimensions, parameters first.
        operator = operator.view(n_params, *[1] * (len(lead) - len(shape) + 3), *shape[1:])
        coefficients = params.movedim(-1, 0)
        coefficients = coefficients.view(
            n_params, *[1] * (len(lead) - params.ndim + 1), *params.shape[:-1], 1, 1
        )
        grad_operator = grad_params = None
        if ctx.needs_input_grad[0]:
            grad_operator = (grad * coefficients).sum_to_size(operator.shape).view(shape)
        if ctx.needs_input_grad[1]:
            sums = _sum_ignoring_padding((operator * grad).flatten(-2))
            grad_params = sums.sum_to_size(coefficients.shape[:-2]).movedim(0, -1).reshape(params.shape)
        return grad_operator, grad_params


def _sum_ignoring_padding(values: Tensor) -> Tensor:
    """Sum over the last dimension that zeros appended to it do not change, bit for bit.

    Fixed blocks of :data:`_SUM_BLOCK` values from the start (the last one completed with zeros) are
    summed, then the block sums added in order (``cumsum``; in float64 on CPU): appended zeros only add
    blocks of zeros. On CUDA the sums are alike up to rounding only.
    """
    length = values.shape[-1]
    full = length // _SUM_BLOCK * _SUM_BLOCK
    tail = values.new_zeros(*values.shape[:-1], 1, _SUM_BLOCK)
    tail[..., 0, : length - full] = values[..., full:]
    blocks = torch.cat([values[..., :full].unflatten(-1, (-1, _SUM_BLOCK)), tail], dim=-2)
    return blocks.sum(dim=-1).cumsum(dim=-1)[..., -1]


def _parameter_first(operator: Tensor) -> Tensor:
    return operator.movedim(-1, 0).contiguous()


def _contrast_loss(
    warp: _LinearWarp,
    params: Tensor,
    weights: Tensor | None,
    sensor_size: tuple[int, int],
    contrast_fn: Callable[..., Tensor],
    sigma: float,
    collapse_weight: float,
    reference: Tensor | None,
    extent: Tensor | None = None,
) -> Tensor:
    """Negative contrasts; with ``extent`` :math:`(K, 2)`, each cluster's image is only its extent of the
    ``sensor_size`` canvas (see :func:`~evseg_torch.level_two.iwe.splat_events`)."""
    if collapse_weight > 0:
        votes = warp.area(params).clamp_min(_MIN_AREA) ** collapse_weight
        weights = votes if weights is None else votes * weights
    images = splat_events(warp.warped(params), sensor_size, weights, sigma, extent=extent)
    if extent is None:
        return -contrast_fn(images, reference)
    return -contrast_fn(images, reference, mask=extent_mask(extent, sensor_size))


def padded_contrast_loss(
    model: MotionModel,
    events: EventBatch,
    params: Tensor,
    weights: Tensor | None = None,
    *,
    sensor_size: tuple[int, int] | None = None,
    objective: str = "variance",
    sigma: float = 1.0,
    collapse_weight: float = DEFAULT_COLLAPSE_WEIGHT,
) -> Tensor:
    r""":func:`contrast_loss` of every window of a padded batch at once, padding weighted 0.

    The windows' events are laid out as :math:`(B, 1, N_{max})`, shared by the K clusters of their
    window, so the warp is linearised once per window and all :math:`B K` images come from one splat.

    Args:
        model: the motion model.
        events: a padded batch (:func:`~evseg_torch.events.batch_windows`), ``xy`` :math:`(B, N_{max}, 2)`.
        params: :math:`(B, K, P)`.
        weights: :math:`(B, K, N_{max})`, or ``None`` for 1 on every real event; padding counts 0 whatever
            its weight holds.
        sensor_size: ``(H, W)``; defaults to ``model.sensor_size``.
        objective: a key of :data:`CONTRAST_OBJECTIVES`.
        sigma: Gaussian blur of the IWEs in pixels.
        collapse_weight: exponent γ of the event-collapse guard; 0 switches it off.

    Returns:
        :math:`(B, K)`; row ``b`` equals :func:`contrast_loss` of window ``b`` alone. Differentiable with
        respect to ``params``, ``weights`` and ``events.xy``.

    Raises:
        ConfigError: for an unknown objective or a negative ``collapse_weight``.
        ShapeError: if the shapes do not fit together or ``events`` is not a padded batch.

    Examples:
        >>> from evseg_torch.events import batch_windows
        >>> from evseg_torch.motion import Affine4
        >>> one = EventBatch(torch.rand(50, 2) * 7, torch.rand(50) * 0.01, torch.ones(50))
        >>> two = EventBatch(torch.rand(30, 2) * 7, torch.rand(30) * 0.01, torch.ones(30))
        >>> padded_contrast_loss(Affine4((8, 8)), batch_windows([one, two]), torch.zeros(2, 3, 4)).shape
        torch.Size([2, 3])
    """
    contrast_fn = _objective(objective)
    if not collapse_weight >= 0:
        raise ConfigError(f"collapse_weight must be >= 0, got {collapse_weight}")
    _check_padded(events)
    batch, longest = events.t.shape
    if params.ndim != 3 or params.shape[0] != batch or params.shape[2] != model.n_params:
        raise ShapeError(
            f"params must be (B, K, {model.n_params}) with B = {batch} windows for the {model.name} model, "
            f"got {tuple(params.shape)}"
        )
    if weights is not None and weights.shape != (batch, params.shape[1], longest):
        raise ShapeError(
            f"weights must be (B, K, N_max) = {(batch, params.shape[1], longest)}, got {tuple(weights.shape)}"
        )
    sensor_size = sensor_size or model.sensor_size
    mask = events.mask[:, None]
    # where, not a product: padding must count 0 even where a caller's padded weights hold NaN.
    weights = mask.to(events.xy.dtype) if weights is None else torch.where(mask, weights, 0.0)
    shared = EventBatch(events.xy[:, None], events.t[:, None], events.p[:, None])
    reference = None
    if objective in _USES_REFERENCE:
        reference = splat_events(shared.xy, sensor_size, weights, sigma)
    warp = _LinearWarp.build(model, shared, with_area=collapse_weight > 0)
    return _contrast_loss(warp, params, weights, sensor_size, contrast_fn, sigma, collapse_weight, reference)


def _check_padded(events: EventBatch) -> None:
    if not isinstance(events, EventBatch) or not events.is_batched:
        raise ShapeError("events must be a padded batch of windows (EventBatch with lengths)")
    if (
        events.t.ndim != 2
        or events.xy.shape != (*events.t.shape, 2)
        or events.lengths.shape != (events.t.shape[0],)
    ):
        raise ShapeError(
            "a padded batch must hold xy (B, N_max, 2), t (B, N_max) and lengths (B,), got "
            f"{tuple(events.xy.shape)}, {tuple(events.t.shape)} and {tuple(events.lengths.shape)}"
        )


def warp_area_element(model: MotionModel, events: EventBatch, params: Tensor) -> Tensor:
    r"""Area element ``det(dx'/dx)`` of the warp at each event: 1 keeps areas, near 0 collapses them.

    The Jacobian of the warp is taken by forward differences of one pixel, exact for velocity fields
    that are affine in ``x`` and accurate to O(t |d²v/dx²|) otherwise. Like
    :func:`~evseg_torch.level_two.iwe.warp_events`, it relies on the models' ``v(x) = J(x) params``.

    Args:
        model: the motion model.
        events: as in :func:`contrast_loss`.
        params: :math:`(K, P)`.

    Returns:
        :math:`(K, N)`.

    Examples:
        >>> from evseg_torch.motion import Affine4
        >>> events = EventBatch(torch.rand(2, 2) * 7, torch.full((2,), 0.1), torch.ones(2))
        >>> warp_area_element(Affine4((8, 8)), events, torch.tensor([[0.0, 0.0, 5.0, 0.0]]))
        tensor([[0.2500, 0.2500]])
    """
    return _LinearWarp.build(model, events).area(params)


class ContrastLoss(nn.Module):
    r"""Module form of :func:`contrast_loss`, to train a network through contrast maximisation.

    Args:
        model: the motion model.
        sensor_size: ``(H, W)``; defaults to ``model.sensor_size``.
        objective: a key of :data:`CONTRAST_OBJECTIVES`.
        sigma: Gaussian blur of the IWEs in pixels.
        collapse_weight: exponent γ of the event-collapse guard; 0 switches it off.
        reduction: ``"none"``, ``"mean"`` or ``"sum"`` over all clusters (and windows).

    Shape:
        - One window: ``events`` an :class:`EventBatch` of N events, ``params`` :math:`(K, P)`,
          ``weights`` :math:`(K, N)`, :math:`(N,)` or ``None``; unreduced output :math:`(K,)`.
        - A padded batch of B windows (:func:`~evseg_torch.events.batch_windows`): ``events`` of
          :math:`(B, N_{max})` events, ``params`` :math:`(B, K, P)`, ``weights`` :math:`(B, K, N_{max})` or
          ``None``, padding weighted 0 either way; unreduced output :math:`(B, K)`. All windows are
          evaluated at once, as tensors.
        - A list of B windows: ``events`` a sequence of B :class:`EventBatch` (their event counts may
          differ), ``params`` :math:`(B, K, P)`, ``weights`` ``None`` or a sequence of B per-window
          weights; unreduced output :math:`(B, K)`. Windows are evaluated one after the other.
        - Reduced output: a scalar.

    Examples:
        >>> from evseg_torch.events import batch_windows
        >>> from evseg_torch.motion import Translation
        >>> events = EventBatch(torch.rand(50, 2) * 7, torch.rand(50) * 0.01, torch.ones(50))
        >>> loss = ContrastLoss(Translation((8, 8)))
        >>> loss([events, events], torch.zeros(2, 3, 2)).shape
        torch.Size([])
        >>> fewer = EventBatch(events.xy[:20], events.t[:20], events.p[:20])
        >>> ContrastLoss(Translation((8, 8)), reduction="none")(
        ...     batch_windows([events, fewer]), torch.zeros(2, 3, 2)
        ... ).shape
        torch.Size([2, 3])
    """

    def __init__(
        self,
        model: MotionModel,
        sensor_size: tuple[int, int] | None = None,
        *,
        objective: str = "variance",
        sigma: float = 1.0,
        collapse_weight: float = DEFAULT_COLLAPSE_WEIGHT,
        reduction: str = "mean",
    ) -> None:
        super().__init__()
        _objective(objective)
        if reduction not in ("none", "mean", "sum"):
            raise ConfigError(f"reduction must be 'none', 'mean' or 'sum', got {reduction!r}")
        self.model = model
        self.sensor_size = _check_sensor_size(sensor_size or model.sensor_size)
        self.objective = objective
        self.sigma = float(sigma)
        self.collapse_weight = float(collapse_weight)
        self.reduction = reduction

    def forward(
        self,
        events: EventBatch | Sequence[EventBatch],
        params: Tensor,
        weights: Tensor | Sequence[Tensor | None] | None = None,
    ) -> Tensor:
        if isinstance(events, EventBatch) and events.is_batched:
            if weights is not None and not isinstance(weights, Tensor):
                raise ShapeError(
                    f"for a padded batch weights must be a tensor (B, K, N_max) or None, got "
                    f"{type(weights).__name__}"
                )
            loss = padded_contrast_loss(
                self.model,
                events,
                params,
                weights,
                sensor_size=self.sensor_size,
                objective=self.objective,
                sigma=self.sigma,
                collapse_weight=self.collapse_weight,
            )
        elif isinstance(events, EventBatch):
            loss = self._window(events, params, weights)
        else:
            if params.ndim != 3 or params.shape[0] != len(events):
                raise ShapeError(
                    f"for a batch of {len(events)} windows params must be (B, K, P) with B = {len(events)}, "
                    f"got {tuple(params.shape)}"
                )
            if weights is None:
                weights = [None] * len(events)
            if len(weights) != len(events):
                raise ShapeError(
                    f"weights must hold one entry per window ({len(events)}), got {len(weights)}"
                )
            loss = torch.stack(
                [self._window(*window) for window in zip(events, params, weights, strict=True)]
            )
        if self.reduction == "mean":
            return loss.mean()
        if self.reduction == "sum":
            return loss.sum()
        return loss

    def _window(self, events: EventBatch, params: Tensor, weights: Tensor | None) -> Tensor:
        return contrast_loss(
            self.model,
            events,
            params,
            weights,
            sensor_size=self.sensor_size,
            objective=self.objective,
            sigma=self.sigma,
            collapse_weight=self.collapse_weight,
        )

    def extra_repr(self) -> str:
        return (
            f"model={self.model.name}, sensor_size={self.sensor_size}, objective={self.objective!r}, "
            f"sigma={self.sigma}, collapse_weight={self.collapse_weight}, reduction={self.reduction!r}"
        )


class ContrastMaximization(nn.Module):
    r"""Refine the motion parameters of K clusters at once by contrast maximisation.

    Each cluster's parameters maximise the contrast of the image of its own (weighted) events, as in
    EMSGC's model refit, but with exact gradients by autograd. For conditioning, the optimiser works in
    pixels of displacement over the window (parameters times ``model.displacement_scale(duration)``), and
    each cluster's loss is divided by its magnitude at the start, so that every cluster weighs alike. With
    ``weights``, each cluster's events of non-zero weight are gathered first, so a fit costs one pass over
    the window's events, not K, and clusters that fill at most a quarter of the sensor are fitted in
    crops around them (see :func:`_crops`). The warp's linear map of the parameters is built once per
    call. Gradients are enabled inside, so a caller may run under ``torch.no_grad()`` or
    ``torch.inference_mode()``.

    A *fit* is the clusters of one window in images of one size (the crops, or the sensor): one parameter
    :math:`(K_f, P)` minimising the sum of their losses, with one optimiser; the clusters are independent,
    so these are separate fits sharing an optimiser, as EMSGC's refit of all models. A padded batch of
    windows runs all its windows' fits in lockstep (:func:`_lockstep`): each keeps an optimiser of its
    own, so that it follows the path it takes alone (no shared line search), while every evaluation of
    the objective and its gradient is one batched pass over all fits still running. A window's result
    then equals its result alone up to rounding (the batched sums add in another order).

    On synthetic edges from 30% off, fits land within 0.5–1% (translation, rotation) and 1–4%
    (4-DOF) of the displacement over the window; what remains is the bias of the objective itself
    (pixel-grid pull of bilinear voting, residual contraction bias), not of the optimiser.

    Args:
        model: the motion model.
        sensor_size: ``(H, W)``; defaults to ``model.sensor_size``.
        objective: a key of :data:`CONTRAST_OBJECTIVES`.
        optimizer: ``"lbfgs"`` (L-BFGS with strong-Wolfe line search) or ``"adam"``.
        max_iter: L-BFGS iterations, or Adam steps.
        lr: step size in conditioned units (pixels); ``None`` means 1 for L-BFGS, 0.1 for Adam.
        sigma: Gaussian blur of the IWEs in pixels (EMSGC: 1).
        collapse_weight: exponent γ of the event-collapse guard; 0 switches it off.
        tol: stop when the summed normalised loss changes by less than this, or (L-BFGS) when the
            step or the gradient is smaller than this in conditioned units.

    Shape:
        - Input: ``events`` an :class:`EventBatch` of N events, ``init_params`` :math:`(K, P)`,
          ``weights`` :math:`(K, N)` or ``None`` (every cluster holds all events); or a padded batch of B
          windows (:func:`~evseg_torch.events.batch_windows`), ``init_params`` :math:`(B, K, P)` and
          ``weights`` :math:`(B, K, N_{max})` or ``None`` (padding never counts). Clusters without events
          (a pool padded to the largest) keep their parameters.
        - Output: refined parameters :math:`(K, P)`, or :math:`(B, K, P)`, in the model's units, detached.

    Examples:
        >>> from evseg_torch.events import batch_windows
        >>> from evseg_torch.motion import Translation
        >>> events = EventBatch(torch.rand(50, 2) * 7, torch.rand(50) * 0.01, torch.ones(50))
        >>> cmax = ContrastMaximization(Translation((8, 8)), max_iter=2)
        >>> cmax(events, torch.zeros(3, 2)).shape
        torch.Size([3, 2])
        >>> fewer = EventBatch(events.xy[:30], events.t[:30], events.p[:30])
        >>> cmax(batch_windows([events, fewer]), torch.zeros(2, 3, 2)).shape
        torch.Size([2, 3, 2])
    """

    def __init__(
        self,
        model: MotionModel,
        sensor_size: tuple[int, int] | None = None,
        *,
        objective: str = "variance",
        optimizer: str = "lbfgs",
        max_iter: int = 20,
        lr: float | None = None,
        sigma: float = 1.0,
        collapse_weight: float = DEFAULT_COLLAPSE_WEIGHT,
        tol: float = 1e-6,
    ) -> None:
        super().__init__()
        _objective(objective)
        if optimizer not in OPTIMIZERS:
            raise ConfigError(f"optimizer must be {' or '.join(map(repr, OPTIMIZERS))}, got {optimizer!r}")
        if isinstance(max_iter, bool) or int(max_iter) != max_iter or max_iter < 1:
            raise ConfigError(f"max_iter must be an integer >= 1, got {max_iter}")
        if lr is not None and not lr > 0:
            raise ConfigError(f"lr must be > 0, got {lr}")
        if not collapse_weight >= 0:
            raise ConfigError(f"collapse_weight must be >= 0, got {collapse_weight}")
        self.model = model
        self.sensor_size = _check_sensor_size(sensor_size or model.sensor_size)
        self.objective = objective
        self.optimizer = optimizer
        self.max_iter = int(max_iter)
        self.lr = float(lr) if lr is not None else (1.0 if optimizer == "lbfgs" else 0.1)
        self.sigma = float(sigma)
        self.collapse_weight = float(collapse_weight)
        self.tol = float(tol)

    def forward(self, events: EventBatch, init_params: Tensor, weights: Tensor | None = None) -> Tensor:
        n_params = self.model.n_params
        if not torch.isfinite(init_params).all():
            raise ModelError("init_params hold NaN or inf: every model's parameters must be finite")
        if events.is_batched:
            _check_padded(events)
            n_windows, longest = events.t.shape
            if init_params.ndim != 3 or init_params.shape[0] != n_windows or init_params.shape[2] != n_params:
                raise ShapeError(
                    f"init_params must be (B, K, {n_params}) with B = {n_windows} windows for the "
                    f"{self.model.name} model, got {tuple(init_params.shape)}"
                )
            if weights is not None and weights.shape != (*init_params.shape[:2], longest):
                raise ShapeError(
                    f"weights must be (B, K, N_max) = {(*init_params.shape[:2], longest)}, "
                    f"got {tuple(weights.shape)}"
                )
            return self._fit_windows(events, init_params.detach(), weights)
        n_events = events.xy.shape[0]
        if events.xy.ndim != 2 or events.xy.shape[1] != 2 or events.t.shape != (n_events,):
            raise ShapeError(
                "events must hold xy (N, 2) and t (N,), "
                f"got {tuple(events.xy.shape)} and {tuple(events.t.shape)}"
            )
        if init_params.ndim != 2 or init_params.shape[1] != n_params:
            raise ShapeError(
                f"init_params must be (K, {n_params}) for the {self.model.name} model, "
                f"got {tuple(init_params.shape)}"
            )
        if weights is not None and weights.shape != (init_params.shape[0], n_events):
            raise ShapeError(
                f"weights must be (K, N) = {(init_params.shape[0], n_events)}, got {tuple(weights.shape)}"
            )
        weights = None if weights is None else weights[None]
        return self._fit_windows(_batch_of_one(events), init_params.detach()[None], weights)[0]

    def _fit_windows(self, events: EventBatch, init: Tensor, weights: Tensor | None) -> Tensor:
        """Fit the clusters of a padded batch: ``init`` :math:`(B, K, P)`, ``weights`` :math:`(B, K, N)`."""
        if torch.is_inference_mode_enabled():
            # The fits need autograd, which inference mode forbids even under enable_grad: they leave it,
            # on ordinary copies of the inference tensors they were given (a caller's evaluation loop).
            with torch.inference_mode(False):
                events = EventBatch(*(_ordinary(field) for field in events))
                return self._fit_windows(events, _ordinary(init), _ordinary(weights))
        n_clusters = init.shape[1]
        mask = events.mask
        durations = torch.where(mask, events.t.abs(), 0).amax(dim=1).tolist()
        members = mask[:, None].to(init.dtype) if weights is None else torch.where(mask[:, None], weights, 0)
        members = members.expand(-1, n_clusters, -1)
        moving = torch.tensor([duration > 0 for duration in durations], device=init.device)
        active = ((members != 0).any(dim=2) & moving[:, None]).flatten()
        index = active.nonzero()[:, 0]
        fitted = init.flatten(0, 1).clone()
        if not len(index):
            return fitted.view_as(init)
        window = torch.div(index, n_clusters, rounding_mode="floor")
        scales = np.stack([self.model.displacement_scale(duration) for duration in durations])
        scale = torch.as_tensor(scales, dtype=init.dtype, device=init.device)[window]
        params = fitted[index]
        own, own_weights = gather_members(events, members.flatten(0, 1)[index], window)
        warp = _LinearWarp.build(self.model, own, with_area=self.collapse_weight > 0)
        fits, origin = _crops(
            warp, own_weights, params, self.sensor_size, window, cropped=weights is not None
        )
        warp = warp._replace(xy=warp.xy - origin[:, None])
        refined = self._solve(warp, own_weights, params * scale, scale, fits) / scale
        fitted[index] = torch.where(torch.isfinite(refined).all(dim=1, keepdim=True), refined, params)
        return fitted.view_as(init)

    def _solve(
        self,
        warp: _LinearWarp,
        weights: Tensor,
        start: Tensor,
        scale: Tensor,
        fits: list[tuple[Tensor, tuple[int, int]]],
    ) -> Tensor:
        """Run every fit to its end, in lockstep; ``start`` and the result :math:`(C, P)` are conditioned.

        Fits in crops and fits on the whole sensor are evaluated apart, so that crops stay small.
        """
        sets = []
        for cropped in (True, False):
            chosen = [(rows, size) for rows, size in fits if (size != self.sensor_size) == cropped]
            if chosen:
                sets.append(_FitSet(self, warp, weights, start, scale, chosen, cropped))
        problems = [(fit_set, fit) for fit_set in sets for fit in range(len(fit_set.fits))]

        def evaluate(running: list[int], values: list[Tensor]) -> list[tuple[Tensor, Tensor]]:
            replies = {}
            for fit_set in sets:
                own = [
                    (i, value) for i, value in zip(running, values, strict=True) if problems[i][0] is fit_set
                ]
                if own:
                    found = fit_set.evaluate([problems[i][1] for i, _ in own], [value for _, value in own])
                    replies.update(zip([i for i, _ in own], found, strict=True))
            return [replies[i] for i in running]

        solved = _lockstep([fit_set.start(fit) for fit_set, fit in problems], self._optimise, evaluate)
        conditioned = torch.empty_like(start)
        for (fit_set, fit), value in zip(problems, solved, strict=True):
            conditioned[fit_set.rows(fit)] = value
        return conditioned

    def _optimise(self, parameter: nn.Parameter, closure: Callable[[], Tensor]) -> None:
        """One fit's whole optimisation; ``closure`` sets the gradient and returns the summed loss."""
        if self.optimizer == "lbfgs":
            torch.optim.LBFGS(
                [parameter],
                lr=self.lr,
                max_iter=self.max_iter,
                tolerance_grad=self.tol,
                tolerance_change=self.tol,
                line_search_fn="strong_wolfe",
            ).step(closure)
            return
        optimizer = torch.optim.Adam([parameter], lr=self.lr)
        previous = None
        for _ in range(self.max_iter):
            loss = float(optimizer.step(closure).detach())
            if previous is not None and abs(previous - loss) < self.tol:
                break
            previous = loss

    def extra_repr(self) -> str:
        return (
            f"model={self.model.name}, sensor_size={self.sensor_size}, objective={self.objective!r}, "
            f"optimizer={self.optimizer!r}, max_iter={self.max_iter}, lr={self.lr}, sigma={self.sigma}, "
            f"collapse_weight={self.collapse_weight}, tol={self.tol}"
        )


class _Rows(NamedTuple):
    """What the loss of some clusters needs: their warp, weights :math:`(R, n)`, scales :math:`(R, P)`,
    image sizes :math:`(R, 2)` in the canvas (``None``: the whole canvas) and reference images."""

    warp: _LinearWarp
    weights: Tensor
    scale: Tensor
    extent: Tensor | None
    reference: Tensor | None

    def select(self, index: Tensor) -> _Rows:
        pick = (None if value is None else value[index] for value in (self.extent, self.reference))
        return _Rows(self.warp.rows(index), self.weights[index], self.scale[index], *pick)


class _FitSet:
    """Fits whose clusters share one canvas, the largest of their image sizes, and are evaluated together.

    Args:
        cmax: the fitting module (objective, blur, collapse guard).
        warp, weights: those of every cluster of the call, :math:`(C, n)`, positions relative to each crop.
        start, scale: every cluster's conditioned start and scale, :math:`(C, P)`.
        fits: each fit's cluster rows (into C) and image size ``(H, W)``.
        cropped: whether the fits are in crops, whose sizes differ between windows. Their images then
            always carry their extents, one size or not, so that a fit's variance is the same, bit for
            bit, whatever the other fits in the canvas (see :func:`image_variance`).
    """

    def __init__(
        self,
        cmax: ContrastMaximization,
        warp: _LinearWarp,
        weights: Tensor,
        start: Tensor,
        scale: Tensor,
        fits: list[tuple[Tensor, tuple[int, int]]],
        cropped: bool,
    ) -> None:
        self.cmax = cmax
        self.index = torch.cat([rows for rows, _ in fits])
        bounds = np.cumsum([0] + [len(rows) for rows, _ in fits]).tolist()
        self.fits = list(itertools.pairwise(bounds))
        sizes = [size for _, size in fits]
        self.size = (max(height for height, _ in sizes), max(width for _, width in sizes))
        extent = None
        if cropped:
            counts = torch.tensor([len(rows) for rows, _ in fits], device=start.device)
            extent = torch.tensor(sizes, device=start.device).repeat_interleave(counts, dim=0)
        warp, weights = warp.rows(self.index), weights[self.index]
        reference = None
        if cmax.objective in _USES_REFERENCE:
            reference = splat_events(warp.xy, self.size, weights, cmax.sigma, extent=extent).detach()
        self.all_rows = _Rows(warp, weights, scale[self.index], extent, reference)
        self.starts = start[self.index]
        with torch.no_grad():
            norm = self._losses(self.all_rows, self.starts).abs()
        self.norm = torch.where(norm > 0, norm, torch.ones_like(norm))
        self._running: tuple[tuple[int, ...], _Rows, Tensor] | None = None

    def start(self, fit: int) -> Tensor:
        first, stop = self.fits[fit]
        return self.starts[first:stop]

    def rows(self, fit: int) -> Tensor:
        first, stop = self.fits[fit]
        return self.index[first:stop]

    def evaluate(self, fits: list[int], values: list[Tensor]) -> list[tuple[Tensor, Tensor]]:
        """Each of ``fits``' summed normalised loss at its conditioned ``values`` and its gradient."""
        if len(fits) == len(self.fits):
            rows, norm = self.all_rows, self.norm
        else:
            # Fits only ever finish, so the rows of those still running change a few times per call.
            if self._running is None or self._running[0] != tuple(fits):
                local = torch.cat([torch.arange(*self.fits[fit], device=self.index.device) for fit in fits])
                self._running = (tuple(fits), self.all_rows.select(local), self.norm[local])
            _, rows, norm = self._running
        conditioned = torch.cat(values).requires_grad_()
        with torch.enable_grad():
            normalised = self._losses(rows, conditioned) / norm
            sizes = [len(value) for value in values]
            totals = [part.sum() for part in normalised.split(sizes)]
            torch.stack(totals).sum().backward()
        grads = conditioned.grad.split(sizes)
        return [(total.detach(), grad) for total, grad in zip(totals, grads, strict=True)]

    def _losses(self, rows: _Rows, conditioned: Tensor) -> Tensor:
        cmax = self.cmax
        return _contrast_loss(
            rows.warp,
            conditioned / rows.scale,
            rows.weights,
            self.size,
            CONTRAST_OBJECTIVES[cmax.objective],
            cmax.sigma,
            cmax.collapse_weight,
            rows.reference,
            rows.extent,
        )


def _lockstep(
    starts: Sequence[Tensor],
    optimise: Callable[[nn.Parameter, Callable[[], Tensor]], None],
    evaluate: Callable[[list[int], list[Tensor]], list[tuple[Tensor, Tensor]]],
) -> list[Tensor]:
    """Minimise independent problems, each with an optimiser of its own, evaluating them together.

    ``optimise(parameter, closure)`` runs one problem's whole optimisation (torch's L-BFGS or Adam); it
    calls ``closure`` whenever it needs the loss and gradient at ``parameter``'s current value. Each
    problem runs in a thread of its own that blocks in ``closure``; once every unfinished problem waits
    there, ``evaluate(problems, values)`` computes all their losses and gradients in one batched pass, and
    they go on. So each problem takes exactly the steps its optimiser takes alone, while the objective is
    evaluated once per step for all. The threads only ever run one at a time between evaluations (the
    optimisers' bookkeeping), so the results do not depend on their scheduling.

    Args:
        starts: each problem's starting value.
        optimise: runs one problem's optimiser to its end.
        evaluate: maps the waiting problems' indices (ascending) and current values to their
            ``(loss, gradient)``.

    Returns:
        Each problem's final value.

    Raises:
        Whatever an optimiser or ``evaluate`` raised, once every problem has stopped.
    """
    parameters = [nn.Parameter(start.clone()) for start in starts]
    requests: queue.SimpleQueue = queue.SimpleQueue()
    reply_queues = [queue.SimpleQueue() for _ in starts]

    def run(index: int) -> None:
        replies = reply_queues[index]

        def closure() -> Tensor:
            requests.put((index, replies))
            reply = replies.get()
            if isinstance(reply, BaseException):
                raise reply
            loss, parameters[index].grad = reply
            return loss

        try:
            optimise(parameters[index], closure)
        except BaseException as error:  # handed to the caller's thread, which raises it
            requests.put((index, error))
        else:
            requests.put((index, None))

    threads = [threading.Thread(target=run, args=(index,), daemon=True) for index in range(len(starts))]
    for thread in threads:
        thread.start()
    running, errors = len(threads), []
    try:
        while running:
            waiting = []
            while len(waiting) < running:
                index, message = requests.get()
                if isinstance(message, queue.SimpleQueue):
                    waiting.append((index, message))
                    continue
                running -= 1
                if message is not None:
                    errors.append(message)
            if not waiting:
                continue
            waiting.sort(key=lambda request: request[0])
            try:
                replies = evaluate(
                    [index for index, _ in waiting], [parameters[index].detach() for index, _ in waiting]
                )
            except BaseException as error:
                replies = [error] * len(waiting)
            for (_, reply_queue), reply in zip(waiting, replies, strict=True):
                reply_queue.put(reply)
    except BaseException as interrupt:
        # Interrupted in this thread (a signal's Stopped while it waits, perhaps between taking a request
        # and noting it): every problem's next reply is the error, so each ends, waiting or not, before the
        # error goes on; no thread is left inside torch while the interpreter exits (which aborts the
        # process). Replies nobody reads any more are harmless.
        for replies in reply_queues:
            replies.put(interrupt)
        for thread in threads:
            thread.join()
        raise
    for thread in threads:
        thread.join()
    if errors:
        raise errors[0]
    return [parameter.detach() for parameter in parameters]


def _crops(
    warp: _LinearWarp,
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


def _objective(name: str) -> Callable[..., Tensor]:
    try:
        return CONTRAST_OBJECTIVES[name]
    except KeyError:
        raise ConfigError(
            f"unknown contrast objective {name!r}; choose one of {sorted(CONTRAST_OBJECTIVES)}"
        ) from None


def _check_image(image: Tensor, name: str) -> None:
    if not isinstance(image, Tensor):
        raise ShapeError(f"{name} must be a torch.Tensor, got {type(image).__name__}")
    if image.ndim < 2:
        raise ShapeError(f"{name} must have shape (..., H, W), got {tuple(image.shape)}")


def _ordinary(tensor: Tensor | None) -> Tensor | None:
    """``tensor``, or an ordinary copy of it if it is an inference tensor (which autograd cannot save)."""
    if tensor is not None and tensor.is_inference():
        return tensor.clone()
    return tensor

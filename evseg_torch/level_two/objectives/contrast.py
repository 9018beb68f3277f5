r"""Contrast objectives and losses of images of warped events (maximised in :mod:`.cmax`).

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

from collections.abc import Callable, Sequence

import torch
from torch import Tensor, nn

from evseg_torch.config import LevelTwoConfig
from evseg_torch.errors import ConfigError, ShapeError
from evseg_torch.events import EventBatch
from evseg_torch.level_two.checks import check_image, check_padded_batch, check_sensor_size
from evseg_torch.level_two.image.splat import splat_events
from evseg_torch.level_two.image.variance import centred_variance, iwe_variance, iwe_variance_and_pullback
from evseg_torch.level_two.image.warp import LinearWarp, area_from, area_gradient
from evseg_torch.motion import MotionModel

__all__ = [
    "CONTRAST_OBJECTIVES",
    "MIN_AREA",
    "REFERENCE_OBJECTIVES",
    "ContrastLoss",
    "check_objective",
    "contrast_loss",
    "image_variance",
    "normalized_variance",
    "padded_contrast_loss",
    "warp_area_element",
    "warped_contrast_loss",
    "warped_contrast_loss_and_grad",
]

MIN_AREA = 1e-6
"""The area element's floor in the event-collapse votes: folded warps (a <= 0) keep a tiny weight and a
finite gradient."""


def image_variance(iwe: Tensor, reference: Tensor | None = None, mask: Tensor | None = None) -> Tensor:
    r"""Variance of an image over its pixels, :math:`\frac{1}{|\Omega|}\sum_x (H(x) - \bar H)^2`.

    Args:
        iwe: :math:`(..., H, W)`.
        reference: unused; accepted so that every objective in :data:`CONTRAST_OBJECTIVES` is called alike.
        mask: optional bool :math:`(..., H, W)`, broadcastable: :math:`\Omega`, the pixels of each image
            (images of different sizes in one canvas, see
            :func:`~evseg_torch.level_two.image.splat.extent_mask`); ``None`` for all.

    Returns:
        :math:`(...)`.

    Examples:
        >>> image_variance(torch.rand(3, 8, 8)).shape
        torch.Size([3])
        >>> image = torch.tensor([[1.0, 3.0, 7.0]])
        >>> image_variance(image, mask=torch.tensor([[True, True, False]]))
        tensor(1.)
    """
    check_image(iwe, "iwe")
    return centred_variance(iwe, mask)[0]


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
    check_image(reference, "reference")
    return image_variance(iwe, mask=mask) / image_variance(reference, mask=mask)


CONTRAST_OBJECTIVES: dict[str, Callable[..., Tensor]] = {
    "variance": image_variance,
    "normalized_variance": normalized_variance,
}
"""Contrast objectives by name; each maps ``(iwe, reference)`` to a contrast to be maximised, and takes a
``mask`` keyword, the pixels of each image, when images of different sizes share one canvas."""

REFERENCE_OBJECTIVES = frozenset({"normalized_variance"})


def contrast_loss(
    model: MotionModel,
    events: EventBatch,
    params: Tensor,
    weights: Tensor | None = None,
    *,
    sensor_size: tuple[int, int] | None = None,
    objective: str = LevelTwoConfig.objective,
    sigma: float = LevelTwoConfig.sigma,
    collapse_weight: float = LevelTwoConfig.collapse_weight,
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
    check_objective(objective)
    if not collapse_weight >= 0:
        raise ConfigError(f"collapse_weight must be >= 0, got {collapse_weight}")
    sensor_size = sensor_size or model.sensor_size
    if params.ndim != 2:
        raise ShapeError(f"params must be (K, P), got {tuple(params.shape)}")
    if weights is not None and weights.shape[-1:] != events.xy.shape[-2:-1]:
        raise ShapeError(
            f"weights must be (K, N) or (N,) with N = {events.xy.shape[-2]}, got {tuple(weights.shape)}"
        )
    reference_variance = None
    if objective in REFERENCE_OBJECTIVES:
        if reference is None:
            reference = splat_events(events.xy, sensor_size, weights, sigma)
        reference_variance = image_variance(reference)
    warp = LinearWarp.build(model, events, with_area=collapse_weight > 0)
    return warped_contrast_loss(
        warp, params, weights, sensor_size, objective, sigma, collapse_weight, reference_variance
    )


def warp_area_element(model: MotionModel, events: EventBatch, params: Tensor) -> Tensor:
    r"""Area element ``det(dx'/dx)`` of the warp at each event: 1 keeps areas, near 0 collapses them.

    The Jacobian of the warp is taken by forward differences of one pixel, exact for velocity fields
    that are affine in ``x`` and accurate to :math:`O(t \, |\partial^2 v / \partial x^2|)` otherwise. Like
    :func:`~evseg_torch.level_two.image.warp.warp_events`, it relies on the models' ``v(x) = J(x) params``.

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
    return LinearWarp.build(model, events).area(params)


def warped_contrast_loss(
    warp: LinearWarp,
    params: Tensor,
    weights: Tensor | None,
    sensor_size: tuple[int, int],
    objective: str,
    sigma: float,
    collapse_weight: float,
    reference_variance: Tensor | None,
    extent: Tensor | None = None,
) -> Tensor:
    """Negative contrasts :math:`(...)` of warped events, ``objective`` a key of
    :data:`CONTRAST_OBJECTIVES` (``reference_variance`` :math:`(...)`, the variance of the reference
    images, for those that need one); with ``extent`` :math:`(..., 2)`, each cluster's image is only its
    extent of the ``sensor_size`` canvas (see :func:`~evseg_torch.level_two.image.splat.splat_events`)."""
    moved = warp.moved(params)
    if collapse_weight > 0:
        votes = area_from(moved).clamp_min(MIN_AREA) ** collapse_weight
        weights = votes if weights is None else votes * weights
    warped = warp.warped_from(moved)  # (..., n, 2)
    lead = warped.shape[:-2]
    weights = warped.new_ones(()) if weights is None else weights
    weights = weights.expand(warped.shape[:-1]).reshape(-1, warped.shape[-2])
    if extent is not None:
        extent = extent.expand(*lead, 2).reshape(-1, 2)
    # Splat, blur and variance as one autograd node (iwe_variance).
    variance = iwe_variance(warped.reshape(-1, *warped.shape[-2:]), weights, sensor_size, sigma, extent)
    variance = variance.view(lead)
    if objective not in REFERENCE_OBJECTIVES:
        return -variance
    return -variance / reference_variance


def warped_contrast_loss_and_grad(
    warp: LinearWarp,
    params: Tensor,
    weights: Tensor,
    sensor_size: tuple[int, int],
    objective: str,
    sigma: float,
    collapse_weight: float,
    reference_variance: Tensor | None,
    mask: Tensor | None = None,
    divisor: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    r""":func:`warped_contrast_loss` of R clusters and its gradient in their parameters, without autograd.

    The fits' evaluations (:mod:`~evseg_torch.level_two.solver.cmax`): the same loss, its gradient chained by
    hand through the variance (:func:`~evseg_torch.level_two.image.variance.iwe_variance_and_pullback`),
    the area-element votes and the linear warp, in a few dozen tensor operations and none of autograd's
    bookkeeping (tested against autograd of :func:`warped_contrast_loss`).

    Args:
        warp: the clusters' warps, events :math:`(R, n)`.
        params: :math:`(R, P)`.
        weights: :math:`(R, n)`.
        sensor_size, objective, sigma, collapse_weight, reference_variance: as in
            :func:`warped_contrast_loss`, for R clusters.
        mask: optional bool :math:`(R, H, W)`, each cluster's pixels of the ``sensor_size`` canvas (the
            :func:`~evseg_torch.level_two.image.splat.extent_mask` of ``warped_contrast_loss``'s ``extent``,
            built once by a caller that evaluates the same clusters many times).
        divisor: optional :math:`(R,)`; the losses are divided by it (each fit's normalisation).

    Returns:
        The losses :math:`(R,)` and their gradients :math:`(R, P)`.
    """
    with torch.no_grad():
        moved = warp.moved(params)
        votes = weights
        if collapse_weight > 0:
            area = area_from(moved)
            clamped = area.clamp_min(MIN_AREA)
            powered = clamped**collapse_weight
            votes = powered * weights
        variance, pullback = iwe_variance_and_pullback(
            warp.warped_from(moved), votes, sensor_size, sigma, mask
        )
        seed = -torch.ones_like(variance)
        if objective in REFERENCE_OBJECTIVES:
            seed = seed / reference_variance
        if divisor is not None:
            seed = seed / divisor
        grad_xy, grad_votes = pullback(seed)
        grad_moved = -grad_xy
        if collapse_weight > 0:
            # d votes / d area = weights γ a^(γ-1) where the area is above the clamp, 0 below it.
            slope = torch.where(area >= MIN_AREA, collapse_weight * powered / clamped, 0.0)
            grad_area = (grad_votes * weights * slope)[..., None] * area_gradient(moved)
            grad_moved = torch.cat([grad_moved, grad_area], dim=-1)
        return seed * variance, warp.params_gradient(grad_moved)


def padded_contrast_loss(
    model: MotionModel,
    events: EventBatch,
    params: Tensor,
    weights: Tensor | None = None,
    *,
    sensor_size: tuple[int, int] | None = None,
    objective: str = LevelTwoConfig.objective,
    sigma: float = LevelTwoConfig.sigma,
    collapse_weight: float = LevelTwoConfig.collapse_weight,
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
    check_objective(objective)
    if not collapse_weight >= 0:
        raise ConfigError(f"collapse_weight must be >= 0, got {collapse_weight}")
    check_padded_batch(events)
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
    reference_variance = None
    if objective in REFERENCE_OBJECTIVES:
        reference_variance = image_variance(splat_events(shared.xy, sensor_size, weights, sigma))
    warp = LinearWarp.build(model, shared, with_area=collapse_weight > 0)
    return warped_contrast_loss(
        warp, params, weights, sensor_size, objective, sigma, collapse_weight, reference_variance
    )


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
        objective: str = LevelTwoConfig.objective,
        sigma: float = LevelTwoConfig.sigma,
        collapse_weight: float = LevelTwoConfig.collapse_weight,
        reduction: str = "mean",
    ) -> None:
        super().__init__()
        check_objective(objective)
        if reduction not in ("none", "mean", "sum"):
            raise ConfigError(f"reduction must be 'none', 'mean' or 'sum', got {reduction!r}")
        self.model = model
        self.sensor_size = check_sensor_size(sensor_size or model.sensor_size)
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


def check_objective(name: str) -> None:
    """``name`` is a key of :data:`CONTRAST_OBJECTIVES` (:class:`ConfigError` otherwise)."""
    if name not in CONTRAST_OBJECTIVES:
        raise ConfigError(f"unknown contrast objective {name!r}; choose one of {sorted(CONTRAST_OBJECTIVES)}")

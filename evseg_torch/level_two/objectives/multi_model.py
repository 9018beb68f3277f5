r"""Contrast loss of several motion models with soft event assignments (Stoffregen et al., ICCV 2019).

Stoffregen et al. ("Event-based motion segmentation by motion compensation", ICCV 2019) segment a
window into K clusters by maximising the summed contrast of K images of warped events, each event
weighting cluster ``k``'s image by its probability :math:`p_{nk}` of belonging there:

.. math::

    \mathcal{L}(P, \Theta) = -\sum_{k=1}^{K} c\Big(\sum_n p_{nk}\, a_{nk}^{\gamma}\,
    \delta\big(\mathbf{x} - \mathbf{x}'_n(\theta_k)\big)\Big)
    + \beta\, \mathrm{KL}\big(\bar p \,\|\, \mathcal{U}_K\big),
    \qquad \bar p_k = \frac{1}{N} \sum_n p_{nk},

with the contrast :math:`c` and the event-collapse guard's area weights :math:`a^{\gamma}` of
:func:`~evseg_torch.level_two.objectives.contrast.contrast_loss` (which computes each cluster's term).

**Degenerate assignments.** The contrast term alone does not keep every cluster in use: from a poor
start, gradient steps on the assignments can hand every event to the cluster whose image is sharpest
and leave the others empty. The second term (weight ``balance_weight``, :math:`\beta`) is the standard
guard of soft clustering (e.g. the entropy term of SCAN, Van Gansbeke et al., ECCV 2020): the KL divergence
of the mean assignment from the uniform one, :math:`\log K - H(\bar p)`. It is 0 when the clusters take
equal shares of the events, :math:`\log(K / (K - 1))` with one cluster empty and :math:`\log K` when
one cluster takes everything. It also pulls clusters of unequal true size towards equal shares, so keep
:math:`\beta` small against the contrast term, whose units are the objective's: with
``"normalized_variance"`` each cluster's contrast is about 1 to 2 (dimensionless), with ``"variance"`` it
grows with the square of the events per pixel (0.05 to 0.3 per cluster on the 90 x 120 synthetic scenes
of the tests). ``balance_weight=0`` (the default) is Stoffregen et al.'s loss.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from evseg_torch.config import LevelTwoConfig
from evseg_torch.errors import ConfigError, ShapeError
from evseg_torch.events import EventBatch
from evseg_torch.level_two.checks import check_padded_batch, check_sensor_size
from evseg_torch.level_two.objectives.contrast import check_objective, padded_contrast_loss
from evseg_torch.motion import MotionModel

__all__ = ["ASSIGNMENT_TOLERANCE", "MultiModelContrastLoss", "multi_model_contrast_loss"]

ASSIGNMENT_TOLERANCE = 1e-3
"""Largest deviation from 1 allowed of an event's assignments summed over the clusters."""

_REDUCTIONS = ("none", "mean", "sum")
# Mean assignments below this count as empty in the balance term: log(p) then stays finite, and so
# does its gradient.
_MIN_SHARE = 1e-12


def multi_model_contrast_loss(
    model: MotionModel,
    events: EventBatch,
    assignments: Tensor,
    params: Tensor,
    *,
    sensor_size: tuple[int, int] | None = None,
    objective: str = LevelTwoConfig.objective,
    sigma: float = LevelTwoConfig.sigma,
    collapse_weight: float = LevelTwoConfig.collapse_weight,
    balance_weight: float = 0.0,
    reduction: str = "mean",
) -> Tensor:
    r"""Summed negative contrast of K clusters' images, events weighted by their soft assignments.

    See the module docstring for the loss. A padded batch is evaluated at once, as tensors, with padding
    weighted 0 (so it changes nothing).

    Args:
        model: the motion model.
        events: one window of N events, or a padded batch of B windows
            (:func:`~evseg_torch.events.batch_windows`).
        assignments: probability of each event to belong to each cluster, :math:`(N, K)` or
            :math:`(B, N_{max}, K)`; non-negative, summing to 1 over K on real events (within
            :data:`ASSIGNMENT_TOLERANCE`); padding entries are ignored.
        params: each cluster's motion, :math:`(K, P)` or :math:`(B, K, P)`, in the model's units.
        sensor_size: ``(H, W)``; defaults to ``model.sensor_size``.
        objective: a key of :data:`~evseg_torch.level_two.objectives.contrast.CONTRAST_OBJECTIVES`.
        sigma: Gaussian blur of the IWEs in pixels.
        collapse_weight: exponent γ of the event-collapse guard; 0 switches it off.
        balance_weight: weight β of the term against degenerate assignments; 0 switches it off.
        reduction: ``"none"`` (one loss per window), ``"mean"`` or ``"sum"`` over the windows.

    Returns:
        :math:`(B,)` with ``"none"`` for a batch, else a scalar; differentiable with respect to
        ``assignments`` and ``params`` (and ``events.xy``). With ``"normalized_variance"`` a cluster
        whose assignments are all 0 has an empty reference image and gives NaN, as in
        :func:`~evseg_torch.level_two.objectives.contrast.contrast_loss` (softmax outputs are never
        exactly 0).

    Raises:
        ConfigError: for an unknown objective or reduction, or a negative ``collapse_weight`` or
            ``balance_weight``.
        ShapeError: if the shapes do not fit together, ``params`` does not have the model's P, or
            ``assignments`` are negative or do not sum to 1 on a real event; ``events`` is not an
            :class:`~evseg_torch.events.EventBatch`.

    Examples:
        >>> from evseg_torch.motion import Affine4
        >>> events = EventBatch(torch.rand(50, 2) * 7, torch.rand(50) * 0.01, torch.ones(50))
        >>> assignments = torch.rand(50, 3).softmax(dim=1)
        >>> multi_model_contrast_loss(Affine4((8, 8)), events, assignments, torch.zeros(3, 4)).shape
        torch.Size([])
    """
    _check_options(objective, collapse_weight, balance_weight, reduction)
    if not isinstance(events, EventBatch):
        raise ShapeError(f"events must be an EventBatch, got {type(events).__name__}")
    single = not events.is_batched
    if single:
        events, assignments, params = _as_batch(events, assignments, params)
    _check_shapes(model, events, assignments, params)
    mask = events.mask
    if not torch.compiler.is_compiling():  # data-dependent checks would break a compiled graph
        _check_assignments(assignments, mask)
    weights = torch.where(mask[..., None], assignments, 0.0).transpose(1, 2)  # (B, K, N_max)
    loss = padded_contrast_loss(
        model,
        events,
        params,
        weights,
        sensor_size=sensor_size,
        objective=objective,
        sigma=sigma,
        collapse_weight=collapse_weight,
    ).sum(dim=1)
    if balance_weight > 0:
        loss = loss + balance_weight * _imbalance(weights, events.lengths)
    if reduction == "mean":
        return loss.mean()
    if reduction == "sum" or single:
        return loss.sum()
    return loss


class MultiModelContrastLoss(nn.Module):
    r"""Module form of :func:`multi_model_contrast_loss`, to train a network that predicts soft
    assignments and motions.

    Args:
        model: the motion model.
        sensor_size: ``(H, W)``; defaults to ``model.sensor_size``.
        objective: a key of :data:`~evseg_torch.level_two.objectives.contrast.CONTRAST_OBJECTIVES`.
        sigma: Gaussian blur of the IWEs in pixels.
        collapse_weight: exponent γ of the event-collapse guard; 0 switches it off.
        balance_weight: weight β of the term against degenerate assignments; 0 switches it off.
        reduction: ``"none"``, ``"mean"`` or ``"sum"`` over the windows.

    Shape:
        - One window: ``events`` of N events, ``assignments`` :math:`(N, K)`, ``params`` :math:`(K, P)`;
          output a scalar.
        - A padded batch of B windows: ``events`` :math:`(B, N_{max})`, ``assignments``
          :math:`(B, N_{max}, K)`, ``params`` :math:`(B, K, P)`; output :math:`(B,)` with
          ``reduction="none"``, else a scalar.

    Examples:
        >>> from evseg_torch.events import batch_windows
        >>> from evseg_torch.motion import Translation
        >>> one = EventBatch(torch.rand(50, 2) * 7, torch.rand(50) * 0.01, torch.ones(50))
        >>> two = EventBatch(torch.rand(30, 2) * 7, torch.rand(30) * 0.01, torch.ones(30))
        >>> loss = MultiModelContrastLoss(Translation((8, 8)), balance_weight=0.1, reduction="none")
        >>> loss(batch_windows([one, two]), torch.rand(2, 50, 3).softmax(dim=2), torch.zeros(2, 3, 2)).shape
        torch.Size([2])
    """

    def __init__(
        self,
        model: MotionModel,
        sensor_size: tuple[int, int] | None = None,
        *,
        objective: str = LevelTwoConfig.objective,
        sigma: float = LevelTwoConfig.sigma,
        collapse_weight: float = LevelTwoConfig.collapse_weight,
        balance_weight: float = 0.0,
        reduction: str = "mean",
    ) -> None:
        super().__init__()
        _check_options(objective, collapse_weight, balance_weight, reduction)
        self.model = model
        self.sensor_size = check_sensor_size(sensor_size or model.sensor_size)
        self.objective = objective
        self.sigma = float(sigma)
        self.collapse_weight = float(collapse_weight)
        self.balance_weight = float(balance_weight)
        self.reduction = reduction

    def forward(self, events: EventBatch, assignments: Tensor, params: Tensor) -> Tensor:
        return multi_model_contrast_loss(
            self.model,
            events,
            assignments,
            params,
            sensor_size=self.sensor_size,
            objective=self.objective,
            sigma=self.sigma,
            collapse_weight=self.collapse_weight,
            balance_weight=self.balance_weight,
            reduction=self.reduction,
        )

    def extra_repr(self) -> str:
        return (
            f"model={self.model.name}, sensor_size={self.sensor_size}, objective={self.objective!r}, "
            f"sigma={self.sigma}, collapse_weight={self.collapse_weight}, "
            f"balance_weight={self.balance_weight}, reduction={self.reduction!r}"
        )


def _imbalance(weights: Tensor, lengths: Tensor) -> Tensor:
    r"""KL divergence of each window's mean assignment from the uniform one, :math:`(B,)`; 0 for an
    empty window.

    Args:
        weights: assignments :math:`(B, K, N_{max})`, 0 on padding.
        lengths: real events per window :math:`(B,)`.
    """
    counts = lengths.to(weights.dtype)
    share = weights.sum(dim=2) / counts.clamp_min(1)[:, None]
    divergence = math.log(weights.shape[1]) + (share * share.clamp_min(_MIN_SHARE).log()).sum(dim=1)
    return torch.where(counts > 0, divergence, 0.0)


def _as_batch(events: EventBatch, assignments: Tensor, params: Tensor) -> tuple[EventBatch, Tensor, Tensor]:
    """One window as a batch of one, after checking that its shapes are one window's."""
    count = events.xy.shape[0]
    if events.xy.shape != (count, 2) or events.t.shape != (count,):
        raise ShapeError(
            f"events must hold xy (N, 2) and t (N,), got {tuple(events.xy.shape)} and {tuple(events.t.shape)}"
        )
    if assignments.ndim != 2 or params.ndim != 2:
        raise ShapeError(
            "for one window assignments must be (N, K) and params (K, P), got "
            f"{tuple(assignments.shape)} and {tuple(params.shape)}"
        )
    lengths = torch.tensor([count], dtype=torch.int64, device=events.xy.device)
    batch = EventBatch(events.xy[None], events.t[None], events.p[None], lengths)
    return batch, assignments[None], params[None]


def _check_shapes(model: MotionModel, events: EventBatch, assignments: Tensor, params: Tensor) -> None:
    check_padded_batch(events)
    batch, longest = events.t.shape
    if assignments.ndim != 3 or params.ndim != 3:
        raise ShapeError(
            f"for a batch of {batch} windows assignments must be (B, N_max, K) and params (B, K, P), got "
            f"{tuple(assignments.shape)} and {tuple(params.shape)}"
        )
    n_clusters = params.shape[1]
    if assignments.shape != (batch, longest, n_clusters) or params.shape[0] != batch:
        raise ShapeError(
            f"assignments must be (B, N_max, K) = {(batch, longest, n_clusters)} to match the events "
            f"(B = {batch}, N_max = {longest}) and params (K = {n_clusters}), got {tuple(assignments.shape)} "
            f"and params {tuple(params.shape)}"
        )
    if n_clusters == 0 or params.shape[2] != model.n_params:
        raise ShapeError(
            f"params must be (..., K, {model.n_params}) with K >= 1 for the {model.name} model, "
            f"got {tuple(params.shape)}"
        )


def _check_assignments(assignments: Tensor, mask: Tensor) -> None:
    real = assignments.detach()[mask]  # (events, K): padding holds anything
    if bool((real < 0).any()):
        raise ShapeError(f"assignments must be >= 0, found {float(real.min()):.3g}")
    deviation = (real.sum(dim=1) - 1).abs()
    if deviation.numel() and not bool((deviation <= ASSIGNMENT_TOLERANCE).all()):
        raise ShapeError(
            f"assignments must sum to 1 over the K clusters on every event (within {ASSIGNMENT_TOLERANCE}), "
            f"found a sum off by {float(deviation.max()):.3g}"
        )


def _check_options(objective: str, collapse_weight: float, balance_weight: float, reduction: str) -> None:
    check_objective(objective)
    if not collapse_weight >= 0:
        raise ConfigError(f"collapse_weight must be >= 0, got {collapse_weight}")
    if not (math.isfinite(balance_weight) and balance_weight >= 0):
        raise ConfigError(f"balance_weight must be a finite number >= 0, got {balance_weight}")
    if reduction not in _REDUCTIONS:
        raise ConfigError(f"reduction must be one of {_REDUCTIONS}, got {reduction!r}")

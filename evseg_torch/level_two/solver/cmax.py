"""Contrast maximisation (CMax) of every cluster's motion: :class:`ContrastMaximization`.

Each cluster's parameters minimise its own contrast loss
(:mod:`~evseg_torch.level_two.objectives.contrast`) on its own gathered events, in a crop around it where
it is small (:mod:`~evseg_torch.level_two.solver.crops`), through the warp's linear map
(:mod:`~evseg_torch.level_two.image.warp`); all clusters of all windows of a call are one batched problem
of the solvers of :mod:`~evseg_torch.level_two.solver.optimizers`. Each evaluation is tensor code
(:func:`~evseg_torch.level_two.objectives.contrast.warped_contrast_loss_and_grad`) or, for float32 fits
on the CPU, one compiled loop per cluster (:mod:`~evseg_torch.kernels.fit`, as
:mod:`evseg_torch.backend` chooses).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from evseg_torch.backend import kernel
from evseg_torch.config import LevelTwoConfig
from evseg_torch.errors import ConfigError, ModelError, ShapeError
from evseg_torch.events import EventBatch, batch_of_one
from evseg_torch.level_two.checks import check_padded_batch, check_sensor_size
from evseg_torch.level_two.image.splat import extent_mask, splat_events
from evseg_torch.level_two.image.warp import LinearWarp
from evseg_torch.level_two.objectives.contrast import (
    MIN_AREA,
    REFERENCE_OBJECTIVES,
    check_objective,
    contrast_loss,
    image_variance,
    warped_contrast_loss_and_grad,
)
from evseg_torch.level_two.solver.crops import fit_crops, gather_members
from evseg_torch.level_two.solver.optimizers import adam, lbfgs
from evseg_torch.motion import MotionModel
from evseg_torch.validation import check_integer

__all__ = ["OPTIMIZERS", "ContrastMaximization"]

OPTIMIZERS = ("lbfgs", "adam")
"""The refits' optimisers (:class:`ContrastMaximization`)."""


class ContrastMaximization(nn.Module):
    r"""Refine the motion parameters of K clusters at once by contrast maximisation.

    Each cluster's parameters maximise the contrast of the image of its own (weighted) events, as in
    EMSGC's model refit, but with exact gradients (chained by hand through the loss,
    :func:`~evseg_torch.level_two.objectives.contrast.warped_contrast_loss_and_grad`). For conditioning, the
    optimiser works in pixels of displacement over the window (parameters times
    ``model.displacement_scale(duration)``), and each cluster's loss is divided by its magnitude at the
    start, so that every cluster weighs alike. With ``weights``, each cluster's events of non-zero weight
    are gathered first, so a fit costs one pass over the window's events, not K, and clusters that fill at
    most a quarter of the sensor are fitted in crops around them (see :func:`fit_crops`). The warp's
    linear map of the parameters is built once per call. The fits need no autograd, so a caller may run
    them under ``torch.no_grad()`` or ``torch.inference_mode()``.

    Every cluster is a problem of its own, as in EMSGC's refit of all models: its parameters minimise its
    own normalised loss. All clusters of all windows of a call are solved together by the batched
    solvers of :mod:`~evseg_torch.level_two.solver.optimizers`, each row following its own path (its own line
    search and stopping), while each evaluation is one batched pass over the clusters still running.
    Clusters in crops and on the whole sensor are evaluated apart (a *fit* is a window's clusters in
    images of one size). A window's result equals its result alone, bit for bit on the CPU.

    On synthetic edges from 30% off, fits land within 0.5–1% (translation, rotation) and 1–4%
    (4-DOF) of the displacement over the window; what remains is the bias of the objective itself
    (pixel-grid pull of bilinear voting, residual contraction bias), not of the optimiser.

    Args:
        model: the motion model.
        sensor_size: ``(H, W)``; defaults to ``model.sensor_size``.
        objective: a key of :data:`CONTRAST_OBJECTIVES`.
        optimizer: ``"lbfgs"`` (L-BFGS, :func:`~evseg_torch.level_two.solver.optimizers.lbfgs`) or ``"adam"``.
        max_iter: L-BFGS iterations, or Adam steps.
        lr: step size in conditioned units (pixels); ``None`` means 1 for L-BFGS, 0.1 for Adam.
        sigma: Gaussian blur of the IWEs in pixels (EMSGC: 1).
        collapse_weight: exponent γ of the event-collapse guard; 0 switches it off.
        tol: a cluster stops when its normalised loss changes by less than this, or (L-BFGS) when
            its step or gradient is smaller than this in conditioned units.

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
        objective: str = LevelTwoConfig.objective,
        optimizer: str = LevelTwoConfig.optimizer,
        max_iter: int = LevelTwoConfig.max_iter,
        lr: float | None = LevelTwoConfig.lr,
        sigma: float = LevelTwoConfig.sigma,
        collapse_weight: float = LevelTwoConfig.collapse_weight,
        tol: float = 1e-6,
    ) -> None:
        super().__init__()
        check_objective(objective)
        if optimizer not in OPTIMIZERS:
            raise ConfigError(f"optimizer must be {' or '.join(map(repr, OPTIMIZERS))}, got {optimizer!r}")
        if lr is not None and not lr > 0:
            raise ConfigError(f"lr must be > 0, got {lr}")
        if not collapse_weight >= 0:
            raise ConfigError(f"collapse_weight must be >= 0, got {collapse_weight}")
        self.model = model
        self.sensor_size = check_sensor_size(sensor_size or model.sensor_size)
        self.objective = objective
        self.optimizer = optimizer
        self.max_iter = check_integer(max_iter, "max_iter", at_least=1)
        self.lr = float(lr) if lr is not None else (1.0 if optimizer == "lbfgs" else 0.1)
        self.sigma = float(sigma)
        self.collapse_weight = float(collapse_weight)
        self.tol = float(tol)

    def forward(
        self,
        events: EventBatch,
        init_params: Tensor,
        weights: Tensor | None = None,
        *,
        max_iter: int | None = None,
    ) -> Tensor:
        """Refined parameters (class docstring); ``max_iter`` replaces the module's for this call."""
        max_iter = self.max_iter if max_iter is None else check_integer(max_iter, "max_iter", at_least=1)
        n_params = self.model.n_params
        if not torch.isfinite(init_params).all():
            raise ModelError("init_params hold NaN or inf: every model's parameters must be finite")
        if events.is_batched:
            check_padded_batch(events)
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
            return self._fit_windows(events, init_params.detach(), weights, max_iter)
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
        return self._fit_windows(batch_of_one(events), init_params.detach()[None], weights, max_iter)[0]

    def losses(self, events: EventBatch, params: Tensor, weights: Tensor) -> Tensor:
        """The contrast loss of each cluster on the whole sensor under this module's objective, blur,
        collapse guard and backend, without a fit (discovery scores its proposals with it).

        Args:
            events: each cluster's own events, ``xy`` :math:`(K, n, 2)` and ``t`` :math:`(K, n)`.
            params: :math:`(K, P)`.
            weights: :math:`(K, n)`.

        Returns:
            :math:`(K,)`, as :func:`~evseg_torch.level_two.objectives.contrast.contrast_loss` up to rounding.
        """
        kernel = None if self.objective in REFERENCE_OBJECTIVES else self._kernel_for(events.xy)
        if kernel is None:
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
        warp = LinearWarp.build(self.model, events, with_area=self.collapse_weight > 0)
        extent = np.tile(np.array(self.sensor_size, dtype=np.int64), (len(params), 1))
        seed = -torch.ones(len(params))
        args = (self.sigma, self.collapse_weight, MIN_AREA, seed)
        return kernel(warp, params, weights, extent, *args, gradient=False)[0]

    def _kernel_for(self, xy: Tensor) -> Callable | None:
        """The compiled evaluation (:mod:`evseg_torch.backend`) for clusters at positions ``xy``: only float32
        fits on the CPU take it; ``None`` for the tensor code."""
        if xy.device.type != "cpu" or xy.dtype != torch.float32:
            return None
        return kernel("fit.loss_and_grad")

    def _fit_windows(self, events: EventBatch, init: Tensor, weights: Tensor | None, max_iter: int) -> Tensor:
        """Fit the clusters of a padded batch: ``init`` :math:`(B, K, P)`, ``weights`` :math:`(B, K, N)`."""
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
        warp = LinearWarp.build(self.model, own, with_area=self.collapse_weight > 0)
        fits, origin = fit_crops(
            warp, own_weights, params, self.sensor_size, window, cropped=weights is not None
        )
        warp = warp._replace(xy=warp.xy - origin[:, None])
        refined = self._solve(warp, own_weights, params * scale, scale, fits, max_iter) / scale
        fitted[index] = torch.where(torch.isfinite(refined).all(dim=1, keepdim=True), refined, params)
        return fitted.view_as(init)

    def _solve(
        self,
        warp: LinearWarp,
        weights: Tensor,
        start: Tensor,
        scale: Tensor,
        fits: list[tuple[Tensor, tuple[int, int]]],
        max_iter: int,
    ) -> Tensor:
        """Minimise every cluster's loss; ``start`` and the result :math:`(C, P)` are conditioned.

        Fits in crops and fits on the whole sensor are evaluated apart, so that crops stay small, but
        solved as one problem set: each round of the solver evaluates both, and its bookkeeping is
        shared (each row's path is its own either way).
        """
        fit_sets = []
        for cropped in (True, False):
            chosen = [(rows, size) for rows, size in fits if (size != self.sensor_size) == cropped]
            if chosen:
                fit_sets.append(_FitSet(self, warp, weights, start, scale, chosen, cropped))
        ends = np.cumsum([len(fit_set.index) for fit_set in fit_sets]).tolist()

        def evaluate(rows: Tensor, conditioned: Tensor) -> tuple[Tensor, Tensor]:
            # Rows are ascending, so each fit set's rows are one slice of them.
            cuts = [0, *torch.searchsorted(rows, torch.tensor(ends, device=rows.device)).tolist()]
            parts = [
                fit_set.evaluate(rows[begin:end] - first, conditioned[begin:end])
                for fit_set, begin, end, first in zip(fit_sets, cuts, cuts[1:], [0, *ends], strict=False)
                if end > begin
            ]
            return torch.cat([loss for loss, _ in parts]), torch.cat([grad for _, grad in parts])

        minimise = lbfgs if self.optimizer == "lbfgs" else adam
        conditioned = torch.empty_like(start)
        index = torch.cat([fit_set.index for fit_set in fit_sets])
        starts = torch.cat([fit_set.starts for fit_set in fit_sets])
        conditioned[index] = minimise(evaluate, starts, max_iter=max_iter, lr=self.lr, tol=self.tol)
        return conditioned

    def extra_repr(self) -> str:
        return (
            f"model={self.model.name}, sensor_size={self.sensor_size}, objective={self.objective!r}, "
            f"optimizer={self.optimizer!r}, max_iter={self.max_iter}, lr={self.lr}, sigma={self.sigma}, "
            f"collapse_weight={self.collapse_weight}, tol={self.tol}"
        )


class _Rows(NamedTuple):
    """What the loss of some clusters needs: their warp, weights :math:`(R, n)`, scales :math:`(R, P)`,
    pixels in the canvas, bool :math:`(R, H, W)` (``None``: the whole canvas, or the compiled evaluation,
    which reads the sizes instead; built once, not at every evaluation), the variances of their reference
    images :math:`(R,)` (objectives that need one) and their images' sizes, int64 :math:`(R, 2)` in NumPy
    (for the compiled evaluation)."""

    warp: LinearWarp
    weights: Tensor
    scale: Tensor
    mask: Tensor | None
    reference_variance: Tensor | None
    extent: np.ndarray

    def select(self, index: Tensor) -> _Rows:
        pick = (None if value is None else value[index] for value in (self.mask, self.reference_variance))
        return _Rows(
            self.warp.rows(index),
            self.weights[index],
            self.scale[index],
            *pick,
            self.extent[index.cpu().numpy()],
        )


class _FitSet:
    """Clusters that share one canvas, the largest of their fits' image sizes, and are evaluated together.

    Args:
        cmax: the fitting module (objective, blur, collapse guard).
        warp, weights: those of every cluster of the call, :math:`(C, n)`, positions relative to each crop.
        start, scale: every cluster's conditioned start and scale, :math:`(C, P)`.
        fits: each fit's cluster rows (into C) and image size ``(H, W)``.
        cropped: whether the fits are in crops, whose sizes differ between windows. Their images then
            always carry their extents, one size or not, so that a cluster's variance is the same, bit
            for bit, whatever the other clusters in the canvas (see :func:`image_variance`).
    """

    def __init__(
        self,
        cmax: ContrastMaximization,
        warp: LinearWarp,
        weights: Tensor,
        start: Tensor,
        scale: Tensor,
        fits: list[tuple[Tensor, tuple[int, int]]],
        cropped: bool,
    ) -> None:
        self.cmax = cmax
        self.index = torch.cat([rows for rows, _ in fits])
        sizes = [size for _, size in fits]
        self.size = (max(height for height, _ in sizes), max(width for _, width in sizes))
        counts = [len(rows) for rows, _ in fits]
        own_sizes = np.repeat(np.array(sizes, dtype=np.int64), counts, axis=0)
        extent = None
        if cropped:
            extent = torch.as_tensor(own_sizes, device=start.device)
        warp, weights = warp.rows(self.index), weights[self.index]
        self.kernel = cmax._kernel_for(warp.xy)
        mask = None if extent is None else extent_mask(extent, self.size)
        reference_variance = None
        if cmax.objective in REFERENCE_OBJECTIVES:
            # A constant of the fits: the variance of each cluster's unwarped image, once.
            reference = splat_events(warp.xy, self.size, weights, cmax.sigma, extent=extent).detach()
            reference_variance = image_variance(reference, mask=mask)
        # The compiled evaluation reads each cluster's extent; only the tensor code needs its mask.
        mask = mask if self.kernel is None else None
        self.all_rows = _Rows(warp, weights, scale[self.index], mask, reference_variance, own_sizes)
        self.starts = start[self.index]
        norm = self._losses_and_grads(self.all_rows, self.starts, None)[0].abs()
        self.norm = torch.where(norm > 0, norm, torch.ones_like(norm))

    def evaluate(self, rows: Tensor, conditioned: Tensor) -> tuple[Tensor, Tensor]:
        """The normalised losses :math:`(R,)` of clusters ``rows`` (into ``starts``) at conditioned values
        :math:`(R, P)`, and their gradients :math:`(R, P)`."""
        if len(rows) == len(self.index):
            chosen, norm = self.all_rows, self.norm
        else:
            chosen, norm = self.all_rows.select(rows), self.norm[rows]
        return self._losses_and_grads(chosen, conditioned.detach(), norm)

    def _losses_and_grads(
        self, rows: _Rows, conditioned: Tensor, norm: Tensor | None
    ) -> tuple[Tensor, Tensor]:
        """Losses (divided by ``norm``) at conditioned values and their gradients in those values."""
        cmax = self.cmax
        if self.kernel is not None:
            seed = -torch.ones(len(rows.weights))
            if cmax.objective in REFERENCE_OBJECTIVES:
                seed = seed / rows.reference_variance
            if norm is not None:
                seed = seed / norm
            losses, grads = self.kernel(
                rows.warp,
                conditioned / rows.scale,
                rows.weights,
                rows.extent,
                cmax.sigma,
                cmax.collapse_weight,
                MIN_AREA,
                seed,
            )
            return losses, grads / rows.scale
        losses, grads = warped_contrast_loss_and_grad(
            rows.warp,
            conditioned / rows.scale,
            rows.weights,
            self.size,
            cmax.objective,
            cmax.sigma,
            cmax.collapse_weight,
            rows.reference_variance,
            rows.mask,
            norm,
        )
        return losses, grads / rows.scale

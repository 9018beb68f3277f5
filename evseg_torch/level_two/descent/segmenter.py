r"""Level two: EMSGC's spatio-temporal graph cut, alternated with contrast-maximisation refits.

The energy over event labels :math:`L` and the models :math:`\Theta` of a pool (EMSGC, Zhou et al. 2021;
the IROS 2021 paper's level two) is

.. math::

    E(L, \Theta) = \lambda_D \sum_k D_k(l_k; \Theta) + \lambda_P \sum_{(k, j)} w_{kj} [l_k \ne l_j]
    + \lambda_M \, |\{l_k\}|,

with the data term of :mod:`~evseg_torch.level_two.energy.data_term`, the spatio-temporal graph of
:mod:`~evseg_torch.level_two.energy.graph` and the label cost of
:mod:`~evseg_torch.level_two.energy.label_cost` per model in use. It is minimised by block-coordinate
descent: data costs of every event under every model; a labelling by α-expansion from the current
labels, empty models dropped and the rest renumbered by size; until the labels settle (or
``n_iter_segmentation`` labellings), each cluster's model refitted by contrast maximisation of its own
events (:mod:`~evseg_torch.level_two.solver.cmax`) and the window labelled again. Beyond the paper, a
settled window then takes discovery's rounds (:mod:`~evseg_torch.level_two.discovery`) and the object
phase (:mod:`~evseg_torch.level_two.objects`); ``discovery_rounds=0`` and ``objects=False`` give the
paper's level two. A stream's window that carries the last one's models in (``carried``) takes a shorter
descent: ``carried_rounds`` labellings, and discovery of what the carried models do not explain
(``carried_discovery``). The steps and the order they come in: :mod:`~evseg_torch.level_two.descent.steps`.

:class:`GraphCutContrastSegmenter` is the driver: each window's state is a
:class:`~evseg_torch.level_two.descent.state.WindowState`, and the windows of a list or padded batch
advance in lockstep, one round at a time: the data costs of every window waiting for a labelling, in
one batched call; each window's labelling, then the steps that are its own (the object phase's); the
proposals of every window that asked for them, in one batched fit; the refits of every window that asked
for one, in one batched fit. Each window's result equals its result alone (bit for bit on the CPU with
one thread). The design in detail: ``docs/design/level_two.md``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from evseg_torch.config import LevelTwoConfig, replace_settings
from evseg_torch.errors import EventFormatError, ShapeError
from evseg_torch.events import EventBatch, batch_of_one, batch_windows
from evseg_torch.graphcut.alpha_expansion import alpha_expansion
from evseg_torch.level_two.checks import check_events, check_labels
from evseg_torch.level_two.descent.batches import (
    chunks,
    memberships,
    padded_pools,
    padded_rows,
    select_windows,
    subsample,
)
from evseg_torch.level_two.descent.clock import StageClock
from evseg_torch.level_two.descent.state import WindowState, start_window
from evseg_torch.level_two.descent.steps import Step, next_step
from evseg_torch.level_two.discovery import Discovery
from evseg_torch.level_two.energy.data_term import DataCost
from evseg_torch.level_two.energy.label_cost import label_cost
from evseg_torch.level_two.image.splat import splat_events
from evseg_torch.level_two.image.warp import warp_events
from evseg_torch.level_two.objectives.contrast import contrast_loss
from evseg_torch.level_two.objects import ObjectPhase
from evseg_torch.level_two.solver.cmax import ContrastMaximization
from evseg_torch.motion import MotionModel, make_motion_model
from evseg_torch.validation import check_integer

__all__ = ["GraphCutContrastSegmenter", "LevelTwoResult"]

# Two sizes that change the speed on the CPU, never a result (a window's result equals its result alone):
# a batch is segmented in groups of consecutive windows of at most this many events (batching amortises
# the fits' per-call overhead until the arrays outgrow the caches) ...
_CPU_BATCH_EVENTS = 1 << 18
# ... and its data term in chunks of windows of at most this many event-model pairs (its passes over
# (B, K, N) arrays are bound by memory beyond). Other devices take the whole batch at once.
_CPU_DATA_TERM_PAIRS = 1 << 18


@dataclass(frozen=True)
class LevelTwoResult:
    """Result of :class:`GraphCutContrastSegmenter` for one window.

    Attributes:
        labels: int64 tensor :math:`(N,)` on the events' device, cluster index of every event in
            ``[0, K')``; cluster 0 is the largest. Level two has no outlier label.
        params: the surviving, refitted models :math:`(K', P)`, ordered as the clusters.
        iwes: each cluster's motion-compensated image of its own events, :math:`(K', H, W)`: bilinear
            voting without blur (EMSGC's output image), so a pixel's value counts events.
        soft_assignments: float :math:`(N, K')` on the events' device, each row summing to 1: a softmax
            over the clusters of each event's negative data cost divided by the segmenter's
            ``soft_temperature``. The costs are those the last labelling used (in ``[0, 255]``, before
            ``lambda_data``, normalised over the pool that labelling was given), restricted to the
            surviving clusters; they see no smoothness term, so their argmax may differ from ``labels``
            where the Potts term overruled an event's own cheapest model.
        energy_history: the energy right after each labelling (one per outer round).
        timings_ms: wall-clock milliseconds spent in ``graph``, ``data_term``, ``labelling``, ``refit``,
            ``discovery`` and ``images`` (asynchronous devices are not synchronised: there, the stages
            that copy to the CPU absorb the rest). A stage run for several windows of a batch at once is
            shared evenly by them, so the windows' timings add up to the batch's.
    """

    labels: Tensor
    params: Tensor
    iwes: Tensor
    soft_assignments: Tensor
    energy_history: tuple[float, ...]
    timings_ms: dict[str, float] = field(default_factory=dict, compare=False)


class _Start(NamedTuple):
    """What one window's descent starts from: its events, initial pool and labels (or ``None``), its
    discovery rounds and whether its pool was carried in by a stream."""

    events: EventBatch
    pool: Tensor
    labels: Tensor | np.ndarray | None
    discovery_rounds: int
    carried: bool


class GraphCutContrastSegmenter(nn.Module):
    r"""Level two of the cascade: EMSGC's graph-cut segmentation with contrast-maximisation refits.

    Every setting (the λ weights, the rounds, the refits' optimiser, discovery, ...) is a field of
    :class:`~evseg_torch.config.LevelTwoConfig`, which holds its default, its documentation and its
    validation: build the segmenter from such a section (:meth:`from_config`, as the pipeline does), or
    give some settings as keywords (``optimizer="adam"``), the others keeping the config's defaults.

    Args:
        model: the motion model, or its name (``translation``, ``affine4``, ``rotation3d``).
        sensor_size: ``(H, W)``.
        config: the settings; ``None`` for :class:`~evseg_torch.config.LevelTwoConfig`'s defaults.
        **settings: fields of :class:`~evseg_torch.config.LevelTwoConfig` replacing those of ``config``.

    Raises:
        ConfigError: a keyword is not a field of the config, or a value is invalid (the message names it).

    Shape:
        - Input: ``events`` one window of N events, ``init_params`` :math:`(K, P)`, optional
          ``init_labels`` :math:`(N,)`; or B windows, as a list or as a padded batch
          (:func:`~evseg_torch.events.batch_windows`), ``init_params`` :math:`(B, K, P)`, :math:`(K, P)`
          shared or a list of B pools, optional ``init_labels`` a list or :math:`(B, N_{max})`.
        - Output: :class:`LevelTwoResult` (or a list of B of them).

    Examples:
        >>> from evseg_torch.events import EventBatch
        >>> xy = torch.randint(0, 32, (500, 2)).float()
        >>> events = EventBatch(xy, torch.linspace(0, 0.01, 500), torch.ones(500))
        >>> segmenter = GraphCutContrastSegmenter("translation", (32, 32), max_iter=3)
        >>> result = segmenter(events, torch.zeros(2, 2))
        >>> result.labels.shape, result.params.shape[1]
        (torch.Size([500]), 2)
        >>> result.soft_assignments.shape == (500, result.params.shape[0])
        True
    """

    def __init__(
        self,
        model: MotionModel | str,
        sensor_size: tuple[int, int],
        config: LevelTwoConfig | None = None,
        **settings,
    ) -> None:
        super().__init__()
        self.config = cfg = replace_settings(config or LevelTwoConfig(), **settings)
        self.sensor_size = tuple(int(v) for v in sensor_size)
        self.model = make_motion_model(model, self.sensor_size) if isinstance(model, str) else model
        self.data_term = DataCost(
            self.model,
            self.sensor_size,
            cfg.data_sigma,
            cfg.data_normalization,
            polarity=cfg.data_polarity,
            margin=None,
            floor_quantile=cfg.data_floor_quantile,
            pool_floor_quantile=cfg.data_pool_floor_quantile,
        )
        refit = {
            "objective": cfg.objective,
            "optimizer": cfg.optimizer,
            "lr": cfg.lr,
            "sigma": cfg.sigma,
            "collapse_weight": cfg.collapse_weight,
        }
        # One contrast maximisation for the refits and discovery's fits; each call gives its iterations.
        self.refit = ContrastMaximization(self.model, self.sensor_size, max_iter=cfg.max_iter, **refit)
        self.discovery = Discovery(self.model, self.sensor_size, cfg, self.refit)
        self.object_phase = ObjectPhase(self.model, self.sensor_size, cfg)

    @classmethod
    def from_config(
        cls, config: LevelTwoConfig, model: MotionModel | str, sensor_size: tuple[int, int]
    ) -> GraphCutContrastSegmenter:
        """The segmenter of a config's ``level_two`` section (for ``model`` and ``sensor_size``)."""
        return cls(model, sensor_size, config)

    def extra_repr(self) -> str:
        settings = ", ".join(
            f"{f.name}={getattr(self.config, f.name)!r}" for f in dataclasses.fields(self.config)
        )
        return f"model={self.model.name}, sensor_size={self.sensor_size}, {settings}"

    def forward(
        self,
        events: EventBatch | Sequence[EventBatch],
        init_params: Tensor | Sequence[Tensor],
        init_labels: Tensor | np.ndarray | Sequence | None = None,
        *,
        discovery_rounds: int | Sequence[int] | None = None,
        carried: bool | Sequence[bool] = False,
    ) -> LevelTwoResult | list[LevelTwoResult]:
        r"""Segment one window, or each window of a list or of a padded batch.

        The windows of a list or batch are segmented together (module docstring, "Batches"); each
        window's result equals its result alone.

        Args:
            events: one window (:class:`~evseg_torch.events.EventBatch`, ``t`` relative to the reference
                time), a list of windows, or a padded batch of windows
                (:func:`~evseg_torch.events.batch_windows`).
            init_params: the initial pool :math:`(K, P)` (level one's models); for several windows, one
                pool shared by all, a list of pools or a tensor :math:`(B, K, P)` of one pool per window.
            init_labels: optional initial labels :math:`(N,)` in ``[0, K)``; for several windows a list of
                them, or for a padded batch :math:`(B, N_{max})` (padding ignored). By default each event
                starts at its cheapest model.
            discovery_rounds: discovery rounds of every window, or a list of one per window; by default
                ``config.discovery_rounds`` (the pipeline gives a window that carries models in fewer).
            carried: whether each window's pool is models a stream carried in (one flag for all, or one
                per window): such a window takes the shorter descent of ``carried_rounds`` and
                ``carried_discovery``.

        Returns:
            :class:`LevelTwoResult`, or a list of them for several windows.

        Raises:
            EventFormatError: if ``events`` is not an EventBatch (or a list of them) or a window is empty.
            ShapeError: if ``init_params`` or ``init_labels`` has the wrong shape, labels are out of range,
                or ``discovery_rounds`` or ``carried`` does not hold one entry per window.
            ModelError: if ``init_params`` hold NaN or inf.
            ConfigError: if a ``discovery_rounds`` is not a non-negative integer.
        """
        if isinstance(events, EventBatch) and not events.is_batched:
            rounds = self._discovery_rounds(discovery_rounds, 1)
            start = _Start(events, init_params, init_labels, rounds[0], _per_window(carried, 1)[0])
            return self._segment(batch_of_one(check_events(events)), [start])[0]
        if isinstance(events, EventBatch):
            windows = [check_events(window) for window in events.unbatch()]
            batch = events
            if isinstance(init_labels, (Tensor, np.ndarray)) and init_labels.ndim == 2:
                if tuple(init_labels.shape) != tuple(events.t.shape):
                    raise ShapeError(
                        f"init_labels of a padded batch must be (B, N_max) = {tuple(events.t.shape)}, "
                        f"got {tuple(init_labels.shape)}"
                    )
                init_labels = [row[: len(window)] for row, window in zip(init_labels, windows, strict=True)]
        elif isinstance(events, Sequence) and not isinstance(events, str):
            windows = [check_events(window) for window in events]
            batch = batch_windows(windows) if windows else None
        else:
            raise EventFormatError(
                f"events must be an EventBatch or a list of them, got {type(events).__name__}"
            )
        count = len(windows)
        if isinstance(init_params, Tensor) and init_params.ndim != 3:
            pools = [init_params] * count
        else:
            pools = list(init_params)
        labels = [None] * count if init_labels is None else list(init_labels)
        if len(pools) != count or len(labels) != count:
            raise ShapeError(
                f"got {count} windows but {len(pools)} pools and {len(labels)} initial labellings"
            )
        rounds = self._discovery_rounds(discovery_rounds, count)
        flags = _per_window(carried, count)
        starts = [_Start(*start) for start in zip(windows, pools, labels, rounds, flags, strict=True)]
        return self._segment(batch, starts) if count else []

    def _discovery_rounds(self, rounds: int | Sequence[int] | None, count: int) -> list[int]:
        """Each window's discovery rounds, checked."""
        if rounds is None:
            return [self.config.discovery_rounds] * count
        each = list(rounds) if isinstance(rounds, Sequence) else [rounds] * count
        if len(each) != count:
            raise ShapeError(f"got {count} windows but {len(each)} discovery_rounds")
        return [check_integer(value, "discovery_rounds") for value in each]

    def contrast_loss(self, events: EventBatch, params: Tensor, labels: Tensor | None = None) -> Tensor:
        r"""Differentiable negative contrast of each cluster's own events under its model.

        This is the refits' objective (:func:`~evseg_torch.level_two.objectives.contrast.contrast_loss`
        with this segmenter's objective, blur and collapse guard), for training a network that predicts
        motion parameters.

        Args:
            events: the window's events.
            params: one model per cluster, :math:`(K, P)`; gradients flow into it.
            labels: cluster of every event, :math:`(N,)` in ``[0, K)``; ``None`` gives every cluster all
                events.

        Returns:
            :math:`(K,)`, lower is sharper.
        """
        events = check_events(events)
        weights = (
            None
            if labels is None
            else memberships(check_labels(labels, events, params), params.shape[0], params.dtype)
        )
        return contrast_loss(
            self.model,
            events,
            params,
            weights,
            sensor_size=self.sensor_size,
            objective=self.config.objective,
            sigma=self.config.sigma,
            collapse_weight=self.config.collapse_weight,
        )

    def _segment(self, batch: EventBatch, starts: list[_Start]) -> list[LevelTwoResult]:
        """Segment the windows of ``batch`` together; on the CPU in groups of consecutive windows."""
        budget = _CPU_BATCH_EVENTS if batch.xy.device.type == "cpu" else None
        groups = chunks([len(start.events) for start in starts], budget)
        if len(groups) == 1:
            return self._segment_together(batch, starts)
        results = []
        for group in groups:
            own = [starts[index] for index in group]
            results += self._segment_together(batch_windows([start.events for start in own]), own)
        return results

    def _segment_together(self, batch: EventBatch, starts: list[_Start]) -> list[LevelTwoResult]:
        """The block-coordinate descent of every window of ``batch``, in lockstep (module docstring)."""
        clock = StageClock(len(starts))
        states = []
        for index, start in enumerate(starts):
            states.append(
                start_window(
                    index,
                    start.events,
                    start.pool,
                    start.labels,
                    self.model,
                    self.sensor_size,
                    self.config,
                    start.discovery_rounds,
                    start.carried,
                )
            )
            clock.lap("graph", states[-1:])
        site_index = padded_rows([state.sites for state in states], batch.t.shape[1], device=batch.xy.device)
        active = states
        while active:
            pending = [state for state in active if not state.costs_ready]
            if pending:
                self._data_costs(batch, pending, site_index)
                clock.lap("data_term", pending)
            for state in active:
                self._label(state)
                clock.lap("labelling", [state])
            proposing = [state for state in active if state.step is Step.PROPOSE]
            if proposing:
                proposals = self.discovery.propose(select_windows(batch, proposing), proposing)
                for state, (params, regions) in zip(proposing, proposals, strict=True):
                    state.add_proposals(params, regions)
                    self._advance(state)
                clock.lap("discovery", proposing)
            config = self.config
            warm_max_iter = config.max_iter if config.warm_max_iter is None else config.warm_max_iter
            for max_iter, first in ((config.max_iter, True), (warm_max_iter, False)):
                # Only the first refit of a window starts from the initial pool (see warm_max_iter).
                chosen = [
                    state
                    for state in active
                    if state.step is Step.REFIT and (len(state.history) == 1) == first
                ]
                if chosen:
                    self._refit(max_iter, select_windows(batch, chosen), chosen)
                    clock.lap("refit", chosen)
            active = [state for state in active if state.step is not Step.STOP]
        results = self._results(batch, states)
        clock.lap("images", states)
        return [
            replace(result, timings_ms=timings)
            for result, timings in zip(results, clock.timings, strict=True)
        ]

    def _data_costs(self, batch: EventBatch, states: list[WindowState], site_index: Tensor) -> None:
        """The windows' data costs, batched, and the graph cuts' cost matrices, copied to the CPU at once.

        Args:
            batch: the padded batch of all windows.
            states: the windows to cost.
            site_index: each event's graph-cut node, -1 on the padding, int64 :math:`(B, N_{max})` for
                every window of ``batch``.
        """
        budget = _CPU_DATA_TERM_PAIRS if batch.xy.device.type == "cpu" else None
        pairs = [len(state.events) * state.params.shape[0] for state in states]
        for chunk in chunks(pairs, budget):
            chunk = [states[index] for index in chunk]
            events = select_windows(batch, chunk)
            params, valid = padded_pools([state.params for state in chunk])
            n_nodes = max(state.n_sites for state in chunk) + 1  # the last for the padding
            with torch.no_grad():
                cost = self.data_term(events, params, valid)  # (B, N_max, K)
                own = site_index[[state.index for state in chunk], : events.t.shape[1]]
                rows = torch.arange(len(chunk), device=own.device)[:, None]
                nodes = n_nodes * rows + torch.where(own < 0, n_nodes - 1, own)
                node_cost = cost.new_zeros(len(chunk) * n_nodes, cost.shape[2])
                node_cost = node_cost.index_add_(
                    0, nodes.flatten(), (self.config.lambda_data * cost).flatten(0, 1)
                )
            # The graph cuts run on the CPU: the one copy back of each round.
            node_cost = node_cost.view(len(chunk), n_nodes, -1).cpu().numpy()
            for row, state in enumerate(chunk):
                n_events, n_models = len(state.events), state.params.shape[0]
                own_cost = node_cost[row, : state.n_sites, :n_models].astype(np.float64)
                if state.objects_on:
                    own_cost += self.object_phase.support_cost(state)
                state.costed(cost[row, :n_events, :n_models], own_cost)

    def _label(self, state: WindowState) -> None:
        """One labelling of a window by α-expansion, then the steps that follow it at once."""
        result = alpha_expansion(
            state.node_cost,
            state.graph,
            smoothness=self.config.lambda_smooth,
            **self.object_phase.label_costs(
                state, label_cost(len(state.events), self.config.lambda_label, self.config.label_cost_events)
            ),
            init_labels=state.node_labels,
            max_cycles=self.config.n_iter_labeling,
        )
        state.labelled(
            result.labels,
            result.energy,
            self.config.label_tol,
            settle_on_reject=state.carried and self.config.carried_discovery == "new",
        )
        self._advance(state)

    def _advance(self, state: WindowState) -> None:
        """Decide a window's next step (:func:`~evseg_torch.level_two.descent.steps.next_step`); the object
        phase's steps are the window's own, so they run at once, until a step that waits for the batch
        (a labelling, a refit) or the end."""
        state.step = next_step(state, self.config.objects)
        while state.step in (Step.SUPPORT, Step.SPLIT):
            if state.step is Step.SUPPORT:
                state.add_support(self.object_phase.support_cost(state))
            else:
                state.split_into(self.object_phase.split(state))
            state.step = next_step(state, self.config.objects)

    def _refit(self, max_iter: int, events: EventBatch, states: list[WindowState]) -> None:
        """Refit every cluster of the windows by contrast maximisation of its own events, all at once."""
        params, _ = padded_pools([state.params for state in states])
        labels = padded_rows([state.labels for state in states], events.t.shape[1], device=events.xy.device)
        members = memberships(labels, params.shape[1], params.dtype)
        if self.config.refit_max_events is not None:
            members = subsample(members, self.config.refit_max_events)
        fitted = self.refit(events, params, members, max_iter=max_iter)
        for row, state in enumerate(states):
            state.refitted(fitted[row, : state.params.shape[0]])
            self._advance(state)

    def _results(self, batch: EventBatch, states: list[WindowState]) -> list[LevelTwoResult]:
        """Each window's result; the images of all windows come from one splat."""
        device = batch.xy.device
        labels = padded_rows([state.labels for state in states], batch.t.shape[1], device=device)
        params, _ = padded_pools([state.params for state in states])
        members = memberships(labels, params.shape[1], params.dtype)
        with torch.no_grad():
            warped = warp_events(self.model, batch.xy[:, None], batch.t[:, None], params)
            iwes = splat_events(warped, self.sensor_size, members, sigma=0.0)
        results = []
        for row, state in enumerate(states):
            n_models = state.params.shape[0]
            # The loop only leaves a window right after a labelling (refits and proposals are always
            # followed by another round), so its final models are that labelling's survivors ``keep``,
            # and ``event_cost[:, keep]`` are their data costs as the labelling saw them.
            final_cost = state.event_cost[:, torch.as_tensor(state.keep, device=device)]
            results.append(
                LevelTwoResult(
                    labels=labels[row, : len(state.events)],
                    params=state.params,
                    iwes=iwes[row, :n_models],
                    soft_assignments=torch.softmax(final_cost / -self.config.soft_temperature, dim=1),
                    energy_history=tuple(state.history),
                )
            )
        return results


def _per_window(flags: bool | Sequence[bool], count: int) -> list[bool]:
    """One flag per window, checked."""
    each = [bool(flags)] * count if isinstance(flags, bool) else [bool(flag) for flag in flags]
    if len(each) != count:
        raise ShapeError(f"got {count} windows but {len(each)} carried flags")
    return each

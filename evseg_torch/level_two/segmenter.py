r"""Level two: EMSGC's spatio-temporal graph cut, alternated with contrast-maximisation refits.

The energy over event labels :math:`L` and the models :math:`\Theta` of a pool (EMSGC, Zhou et al. 2021;
the IROS 2021 paper's level two) is

.. math::

    E(L, \Theta) = \lambda_D \sum_k D_k(l_k; \Theta) + \lambda_P \sum_{(k, j)} w_{kj} [l_k \ne l_j]
    + \lambda_M \, |\{l_k\}|,

with the data term of :mod:`~evseg_torch.level_two.data_term`, the spatio-temporal graph of
:mod:`~evseg_torch.level_two.graph` and a label cost :math:`\lambda_M` per model in use. It is minimised by
block-coordinate descent (EMSGC ``applySegmentation_GMM``), for at most ``n_iter_segmentation`` rounds:

1. data costs of every event under every current model;
2. labelling by α-expansion (``n_iter_labeling`` cycles), starting from the current labels (first round:
   each event's, or site's, cheapest model);
3. empty models are dropped and the rest renumbered by size, largest first;
4. stop when one cluster remains, when at most a fraction ``label_tol`` of the labels changed, or when
   the energy equals the previous round's; but the first time this happens (``discovery_rounds``
   times in all), **discovery** proposes new models and the descent goes on with them;
5. each cluster's model is refitted by contrast maximisation of its own events, warm-started at the
   current parameters.

Discovery (beyond the paper, whose level two only prunes level one's pool, so that a motion level one
missed or merged with another is never recovered): regions of events that may follow a motion of their
own (a cluster's spatially separate groups, the halves of a cluster other than the largest, the union of
two touching clusters; see :mod:`~evseg_torch.level_two.discovery`) each get a model by contrast
maximisation (``discovery_max_iter`` iterations on at most 1500 of its events, from the sharper of two
starts); a proposal that compensates its region less sharply than the region's own model, or that
collapses it (changes its area by more than 10%), is dropped. The rest join the pool, and the next
labelling, by the same energy and its label cost, decides which are used; unused ones are dropped
like any empty model. Each window proposes at most ``discovery_max_proposals`` models
``discovery_rounds`` times, and stops proposing once a round's proposals were all rejected, so split,
proposal and the label cost's merging cannot oscillate. ``discovery_rounds=0`` is the paper's level two.

Objects (beyond the paper; :mod:`~evseg_torch.level_two.objects`): once discovery is done and the labels
have settled, an *object phase* makes every non-background cluster one object. It labels again with a
support term (a label pays ``object_support_cost`` for each event its model compensates away from the
label's own object groups), then splits clusters whose compensated events form separate objects,
``object_splits`` times at most, each split refitting the parts and labelling once more. It comes last so
that the descent's early rounds, whose labels are still poor, are those of EMSGC; a support built on
them would keep their mistakes. ``objects=False`` gives the paper's per-motion clusters.

The label cost scales with the window (``label_cost_events``): :math:`\lambda_M(N) = \lambda_{label}
\max(1, N / N_0)`. The data cost that a spurious model saves grows with the events it takes over, so a
fixed cost lets spurious labels in on dense windows; on sparse windows (below :math:`N_0` events) the
cost stays ``lambda_label``, so a small object keeps its own label there.

Deviations from EMSGC, each measured on the synthetic scenes of :func:`~evseg_torch.synthetic.make_scene`
(``benchmarks/bench_level_two.py``; ~30k events, 3–4 models, 2 CPU cores):

* the refitted models feed the next round's data term (the EMSGC release keeps reading the initial
  pool): this is the block-coordinate descent the papers describe;
* the data term's ``"relative"`` normalisation, per-polarity IWEs and an automatic margin around the
  IWEs by default (see :mod:`~evseg_torch.level_two.data_term`);
* the refits see at most ``refit_max_events`` events per cluster, every s-th of the cluster in time
  order (a deterministic, evenly spread subsample): the models come from level one already close, the
  variance objective of a few thousand events has the same maximum, and the refit's cost is
  proportional to the events it warps;
* the loop stops once at most ``label_tol`` of the labels changed (EMSGC: none), which saves the
  last rounds that only flip a few boundary events;
* the graph cut labels *sites*, not events (``site_time_slices``, see
  :func:`~evseg_torch.level_two.graph.site_graph`): the events of one pixel within one time slice of
  the window share a label, their data costs summed and their edges merged, so the energy is EMSGC's
  restricted to such labellings. With one slice the cut has 12–15k nodes and ~40k edges instead of
  ~30k and ~155k and α-expansion is 4–7 times faster; on the benchmark windows one labelling's energy
  rises by 0.0–0.3%, and on the 10 scenes of the slow quality test accuracy stays within ±0.01 and the
  worst object's IoU within ±0.03 on 9 of 10 scenes (the tenth, seed 0, swings between 0.71 and 0.88
  accuracy under any small change of the settings, on events and on sites alike);
* only the first refit runs ``max_iter`` optimiser iterations; the later ones start from the previous
  refit and run ``warm_max_iter``: after the first refit the models move by less than 0.5 px of
  displacement per round, and 3 iterations take them there (about 40% of a 10-iteration refit).

Energies. Each labelling never raises the energy *for the models it was given* (α-expansion accepts only
improving moves, from the current labels). A refit changes the data term, so energies of different rounds
measure different functions and need not decrease; ``energy_history`` records the energy right after each
labelling. On sites, given initial labels are first made constant per site (each site takes its events'
most frequent label), which can raise the energy of labels that differ within a site; the labels this
segmenter returns are constant per site already, for the same ``site_time_slices``.

Devices. Events and parameters may live on any device; the data term, refits, discovery's fits and the
images run there. The graph, α-expansion and discovery's grouping of events run on the CPU (NumPy,
PyMaxflow, OpenCV), on copies of the event coordinates (once per window), of the :math:`(S, K)` cost
matrices of the sites (once per round) and of the events' own data costs (once per discovery). The graph
depends on the events only: it is built, and its cut-graph node numbering chosen
(:func:`~evseg_torch.graphcut.alpha_expansion.potts_graph`), once per window.

Batches. A list or a padded batch of windows is segmented in lockstep: in each round, the data costs of
every window still running come from one batched call (pools padded to the largest, padded models never
win), their cost matrices are copied to the CPU at once, each window is labelled by its own graph cut,
and the refits, and discovery's fits, of all windows are one batched contrast maximisation
(:class:`~evseg_torch.level_two.cmax.ContrastMaximization`: every cluster its own problem of one
batched solver). Windows that stop drop out of the later rounds. Each window's result equals its
result alone: on the CPU with one intra-op thread bit for bit (the data term and the fits' sums are
independent of the padding and of the other windows); with more threads, or on CUDA, up to the rounding
of reductions that torch splits by the size of the whole batch, which the descent can amplify (measured
on 2 threads: 330 of 8028 labels of a 180×240 window changed when two other windows joined it).
The graph cuts run one after the other: PyMaxflow holds the GIL while it computes a maximum flow
(measured: two cuts in two threads take as long as one after the other), so threads gain nothing.
On the CPU, where large batched arrays outgrow the caches, a batch is segmented in groups of a few
hundred thousand events, and the data term in chunks of a window or two (same results).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from evseg_torch.config import LevelTwoConfig, replace_settings
from evseg_torch.errors import EventFormatError, ModelError, ShapeError
from evseg_torch.events import EventBatch, batch_windows
from evseg_torch.graphcut.alpha_expansion import PottsGraph, alpha_expansion, potts_graph
from evseg_torch.level_two.cmax import ContrastMaximization
from evseg_torch.level_two.contrast import contrast_loss, warp_area_element
from evseg_torch.level_two.crops import gather_members
from evseg_torch.level_two.data_term import DataCost
from evseg_torch.level_two.discovery import (
    candidate_regions,
    centroid_velocity,
    recentred,
    translation_params,
)
from evseg_torch.level_two.graph import event_graph, site_graph
from evseg_torch.level_two.iwe import _batch_of_one, splat_events, warp_events
from evseg_torch.level_two.objects import cluster_groups, split_objects, support_cost
from evseg_torch.motion import MotionModel, make_motion_model

__all__ = ["DEFAULT_SOFT_TEMPERATURE", "GraphCutContrastSegmenter", "LevelTwoResult"]

# A proposal only needs to show whether a region has a sharper motion of its own; an even subsample of
# this many events per region finds it, at a fraction of the cost of fitting whole regions.
_PROPOSAL_MAX_EVENTS = 1500
# Largest mean change of its region's area (the warp's area element) a proposal may make.
_MAX_AREA_CHANGE = 0.1
# On the CPU, a batch is segmented in groups of consecutive windows of at most this many events: batching
# amortises the refits' and discovery's per-call overhead (measured on 40k-event windows, 2 cores: refits
# 178 -> 113 ms per window and discovery 401 -> 261 in batches of 8), but batches of 32 lost most of it
# (157 and 358) to arrays that outgrow the caches.
_CPU_BATCH_EVENTS = 1 << 18
# On the CPU, the data term of a batch runs in chunks of windows of at most this many event-model pairs:
# its dozens of passes over (B, K, N) arrays are bound by memory once these outgrow the caches (measured
# on 40k-event windows with 4 models, 2 cores: 64-66 ms per window in chunks of 1-2 windows, 80-84 in
# chunks of 4-8). Other devices cost the whole batch at once. The costs are the same either way.
_CPU_DATA_TERM_PAIRS = 1 << 18

DEFAULT_SOFT_TEMPERATURE = LevelTwoConfig.soft_temperature
"""Default temperature of :attr:`LevelTwoResult.soft_assignments`, in data-cost units (of ``[0, 255]``).

Chosen by temperature scaling: of the temperatures below, it minimises the mean negative log-likelihood of
the true layer on the 10 scenes of the slow quality test of ``tests/level_two/test_segmenter.py``
(``make_scene((180, 240), 0.03, n_objects=1 + seed % 3, rng=seed)``, seeds 0-9, default segmenter from
perturbed true models plus two spurious ones; each cluster matched to a layer by
:func:`~evseg_torch.metrics.match_clusters`, noise and ambiguous events left out). The argmax of the soft
assignments does not depend on the temperature: it equals the hard label on 0.80 of the events on average
(0.65-0.89 per scene; the Potts term overrules the rest), and is the true layer on 0.81 of the
ground-truth events.

===========  ======================  ===============================  ======================
temperature  mean max-probability    mean probability of hard label   NLL of the true layer
===========  ======================  ===============================  ======================
2            0.95                    0.80                             1.67
5            0.91                    0.79                             0.85
10           0.86                    0.77                             0.55
15           0.82                    0.75                             0.48
20           0.79                    0.74                             0.46
30           0.74                    0.70                             0.48
40           0.70                    0.67                             0.51
80           0.58                    0.57                             0.65
===========  ======================  ===============================  ======================

At 20 the soft assignments are also calibrated: their mean max-probability on the ground-truth events
(0.80) matches the fraction of those events whose argmax is the true layer (0.81).
"""


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


def _check_events(events) -> EventBatch:
    if not isinstance(events, EventBatch):
        raise EventFormatError(
            f"level two expects an EventBatch (see events.to_torch), got {type(events).__name__}"
        )
    count = len(events)
    if count == 0:
        raise EventFormatError("level two got a window with 0 events")
    if events.xy.shape != (count, 2) or events.p.shape != (count,):
        raise ShapeError(
            f"EventBatch fields must be xy (N, 2), t (N,), p (N,); got {tuple(events.xy.shape)}, "
            f"{tuple(events.t.shape)}, {tuple(events.p.shape)}"
        )
    return events


_STAGES = ("graph", "data_term", "labelling", "refit", "discovery", "images")


@dataclass
class _Window:
    """One window's block-coordinate descent as the segmenter steps it, round by round.

    ``sites`` maps each event to its graph-cut node (the event itself without sites), ``xy`` holds its
    integer pixels on the CPU (for discovery), ``event_cost`` the last data costs :math:`(N, K)` and
    ``node_cost`` their sums per node for the graph cut (``costs_ready`` when they are set for the next
    labelling already); ``step`` is what follows the last labelling: ``"refit"``, ``"propose"``
    (discovery), ``"label"`` (again, with proposals or the object phase's support) or ``"stop"``.
    ``objects_on`` once the object phase has begun, ``splits_left`` its splits still allowed, ``regions``
    the events of each proposal (its first support).
    """

    index: int
    events: EventBatch
    xy: np.ndarray
    polarity: np.ndarray
    graph: PottsGraph
    sites: np.ndarray
    n_sites: int
    params: Tensor
    labels: np.ndarray | None
    node_labels: np.ndarray | None
    rounds_left: int
    discoveries_left: int
    splits_left: int
    history: list[float] = field(default_factory=list)
    regions: list[np.ndarray] = field(default_factory=list)
    objects_on: bool = False
    costs_ready: bool = False
    proposed_from: int | None = None
    event_cost: Tensor | None = None
    node_cost: np.ndarray | None = None
    keep: np.ndarray | None = None
    step: str = "label"


class _Candidates(NamedTuple):
    """One window's candidate regions for discovery: their members :math:`(R, N)` (an even subsample),
    the start of each one's fit and the model of the cluster it came from :math:`(R, P)`, and its
    gathered events and weights :math:`(R, n)`."""

    members: Tensor
    start: Tensor
    origin: Tensor
    own: EventBatch
    weights: Tensor


class _Clock:
    """Wall-clock milliseconds per stage and window; a stage run for several windows at once is shared
    evenly by them, so the windows' timings add up to the batch's."""

    def __init__(self, n_windows: int) -> None:
        self.timings = [dict.fromkeys(_STAGES, 0.0) for _ in range(n_windows)]
        self._last = time.perf_counter()

    def lap(self, stage: str, windows: Sequence[_Window]) -> None:
        now = time.perf_counter()
        share = 1e3 * (now - self._last) / len(windows)
        for window in windows:
            self.timings[window.index][stage] += share
        self._last = now


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
            cfg.sigma,
            cfg.data_normalization,
            polarity=cfg.data_polarity,
            margin=None,
        )
        refit = {
            "objective": cfg.objective,
            "optimizer": cfg.optimizer,
            "lr": cfg.lr,
            "sigma": cfg.sigma,
            "collapse_weight": cfg.collapse_weight,
        }
        warm_max_iter = cfg.max_iter if cfg.warm_max_iter is None else cfg.warm_max_iter
        self.refit = ContrastMaximization(self.model, self.sensor_size, max_iter=cfg.max_iter, **refit)
        self.warm_refit = ContrastMaximization(self.model, self.sensor_size, max_iter=warm_max_iter, **refit)
        self.proposal_fit = ContrastMaximization(
            self.model, self.sensor_size, max_iter=cfg.discovery_max_iter, **refit
        )

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

        Returns:
            :class:`LevelTwoResult`, or a list of them for several windows.

        Raises:
            EventFormatError: if ``events`` is not an EventBatch (or a list of them) or a window is empty.
            ShapeError: if ``init_params`` or ``init_labels`` has the wrong shape, or labels out of range.
            ModelError: if ``init_params`` hold NaN or inf.
        """
        if isinstance(events, EventBatch) and not events.is_batched:
            return self._segment(
                _batch_of_one(_check_events(events)), [events], [init_params], [init_labels]
            )[0]
        if isinstance(events, EventBatch):
            windows = [_check_events(window) for window in events.unbatch()]
            batch = events
            if isinstance(init_labels, (Tensor, np.ndarray)) and init_labels.ndim == 2:
                if tuple(init_labels.shape) != tuple(events.t.shape):
                    raise ShapeError(
                        f"init_labels of a padded batch must be (B, N_max) = {tuple(events.t.shape)}, "
                        f"got {tuple(init_labels.shape)}"
                    )
                init_labels = [row[: len(window)] for row, window in zip(init_labels, windows, strict=True)]
        elif isinstance(events, Sequence) and not isinstance(events, str):
            windows = [_check_events(window) for window in events]
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
        return self._segment(batch, windows, pools, labels) if count else []

    def contrast_loss(self, events: EventBatch, params: Tensor, labels: Tensor | None = None) -> Tensor:
        r"""Differentiable negative contrast of each cluster's own events under its model.

        This is the refits' objective (:func:`~evseg_torch.level_two.contrast.contrast_loss` with this
        segmenter's objective, blur and collapse guard), for training a network that predicts motion
        parameters.

        Args:
            events: the window's events.
            params: one model per cluster, :math:`(K, P)`; gradients flow into it.
            labels: cluster of every event, :math:`(N,)` in ``[0, K)``; ``None`` gives every cluster all
                events.

        Returns:
            :math:`(K,)`, lower is sharper.
        """
        events = _check_events(events)
        weights = (
            None
            if labels is None
            else _members(self._check_labels(labels, events, params), params.shape[0], params.dtype)
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

    def _segment(
        self, batch: EventBatch, windows: list[EventBatch], pools: list, init_labels: list
    ) -> list[LevelTwoResult]:
        """Segment the windows of ``batch`` together; on the CPU in groups of consecutive windows."""
        budget = _CPU_BATCH_EVENTS if batch.xy.device.type == "cpu" else None
        groups = _chunks([len(window) for window in windows], budget)
        if len(groups) == 1:
            return self._segment_together(batch, windows, pools, init_labels)
        results = []
        for group in groups:
            own = [windows[index] for index in group]
            results += self._segment_together(
                batch_windows(own),
                own,
                [pools[index] for index in group],
                [init_labels[index] for index in group],
            )
        return results

    def _segment_together(
        self, batch: EventBatch, windows: list[EventBatch], pools: list, init_labels: list
    ) -> list[LevelTwoResult]:
        """The block-coordinate descent of every window of ``batch``, in lockstep (module docstring)."""
        clock = _Clock(len(windows))
        states = []
        for index, (events, pool, labels) in enumerate(zip(windows, pools, init_labels, strict=True)):
            states.append(self._start(index, events, pool, labels))
            clock.lap("graph", states[-1:])
        site_index = _padded_rows([state.sites for state in states], batch.t.shape[1], device=batch.xy.device)
        active = states
        while active:
            pending = [state for state in active if not state.costs_ready]
            if pending:
                self._data_costs(batch, pending, site_index)
                clock.lap("data_term", pending)
            for state in active:
                state.costs_ready = False
                self._label(state)
                clock.lap("labelling", [state])
            proposing = [state for state in active if state.step == "propose"]
            if proposing:
                self._discover(_select(batch, proposing), proposing)
                clock.lap("discovery", proposing)
            for refit, first in ((self.refit, True), (self.warm_refit, False)):
                # Only the first refit of a window starts from the initial pool (see warm_max_iter).
                chosen = [
                    state for state in active if state.step == "refit" and (len(state.history) == 1) == first
                ]
                if chosen:
                    self._refit(refit, _select(batch, chosen), chosen)
                    clock.lap("refit", chosen)
            active = [state for state in active if state.step != "stop"]
        results = self._results(batch, states)
        clock.lap("images", states)
        return [
            replace(result, timings_ms=timings)
            for result, timings in zip(results, clock.timings, strict=True)
        ]

    def _start(self, index: int, events: EventBatch, init_params: Tensor, init_labels) -> _Window:
        """A window's graph and starting point."""
        params = self._check_params(init_params, events)
        labels = (
            None if init_labels is None else self._check_labels(init_labels, events, params).cpu().numpy()
        )
        if self.config.site_time_slices is None:
            edges, weights = event_graph(
                events, sensor_size=self.sensor_size, temporal_edges=self.config.temporal_edges
            )
            sites = np.arange(len(events))
        else:
            sites, edges, weights = site_graph(
                events,
                sensor_size=self.sensor_size,
                time_slices=self.config.site_time_slices,
                temporal_edges=self.config.temporal_edges,
            )
        n_sites = int(sites.max()) + 1
        # Sites are numbered in row-major pixel order, already local; events are in time order.
        graph = potts_graph(edges, weights, n_nodes=n_sites, reorder=self.config.site_time_slices is None)
        node_labels = labels
        if labels is not None and self.config.site_time_slices is not None:
            node_labels = _site_majority(labels, sites, n_sites)
        return _Window(
            index=index,
            events=events,
            xy=events.xy.detach().cpu().numpy().astype(np.int64),
            polarity=events.p.detach().cpu().numpy(),
            graph=graph,
            sites=sites,
            n_sites=n_sites,
            params=params,
            labels=labels,
            node_labels=node_labels,
            rounds_left=self.config.n_iter_segmentation,
            discoveries_left=self.config.discovery_rounds,
            splits_left=self.config.object_splits,
        )

    def _data_costs(self, batch: EventBatch, states: list[_Window], site_index: Tensor) -> None:
        """The windows' data costs, batched, and the graph cuts' cost matrices, copied to the CPU at once.

        Args:
            batch: the padded batch of all windows.
            states: the windows to cost.
            site_index: each event's graph-cut node, -1 on the padding, int64 :math:`(B, N_{max})` for
                every window of ``batch``.
        """
        budget = _CPU_DATA_TERM_PAIRS if batch.xy.device.type == "cpu" else None
        pairs = [len(state.events) * state.params.shape[0] for state in states]
        for chunk in _chunks(pairs, budget):
            chunk = [states[index] for index in chunk]
            events = _select(batch, chunk)
            params, valid = _padded_pools([state.params for state in chunk])
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
                state.event_cost = cost[row, :n_events, :n_models]
                state.node_cost = node_cost[row, : state.n_sites, :n_models].astype(np.float64)
                if state.objects_on:
                    state.node_cost += self._support_cost(state)

    def _label(self, state: _Window) -> None:
        """One labelling of a window by α-expansion, then its renumbering and what comes next."""
        state.rounds_left -= 1
        result = alpha_expansion(
            state.node_cost,
            state.graph,
            smoothness=self.config.lambda_smooth,
            label_cost=self._label_cost(len(state.events)),
            init_labels=state.node_labels,
            max_cycles=self.config.n_iter_labeling,
        )
        event_labels = result.labels[state.sites]
        mapping, keep = _renumber_by_size(event_labels, state.params.shape[0])
        state.node_labels, labels = mapping[result.labels], mapping[event_labels]
        state.params = state.params[torch.as_tensor(keep, device=state.params.device)]
        converged = (
            len(keep) == 1
            or (bool(state.history) and result.energy == state.history[-1])
            or (state.labels is not None and _changed(state.labels, labels, keep) <= self.config.label_tol)
        )
        if state.proposed_from is not None and not np.any(keep >= state.proposed_from):
            state.discoveries_left = 0  # every proposal was rejected: proposing again would repeat them
        state.proposed_from = None
        state.regions = []
        state.labels, state.keep = labels, keep
        state.history.append(result.energy)
        done = converged or state.rounds_left == 0
        if not done:
            state.step = "refit"
        elif state.discoveries_left > 0:
            state.discoveries_left -= 1
            state.step = "propose"
        else:
            state.step = self._object_step(state)

    def _object_step(self, state: _Window) -> str:
        """What follows a settled labelling once discovery is done: the object phase
        (:mod:`~evseg_torch.level_two.objects`). Its first step labels again with the support term, when
        some event lies outside its own cluster's support; later ones split clusters of separate objects
        and refit the parts, ``object_splits`` times at most; then the window stops."""
        if not self.config.objects:
            return "stop"
        if not state.objects_on:
            state.objects_on = True
            support = self._support_cost(state)
            if np.any(support[np.arange(state.n_sites), state.node_labels] > 0):
                # No model moved since this labelling: its data costs stand, for the surviving models.
                state.event_cost = state.event_cost[
                    :, torch.as_tensor(state.keep, device=state.params.device)
                ]
                state.node_cost = state.node_cost[:, state.keep] + support
                state.costs_ready = True
                state.rounds_left = max(state.rounds_left, 1)
                return "label"
        if state.splits_left > 0 and self._split(state):
            state.splits_left -= 1
            state.rounds_left = max(state.rounds_left, 1)
            return "refit"
        return "stop"

    def _discover(self, events: EventBatch, states: list[_Window]) -> None:
        """Propose models for the windows' candidate regions; a window with proposals labels again.

        The regions and the fits' starts are found per window (NumPy and a few small tensor operations);
        the fits, most of discovery's time, run for all windows at once.
        """
        own = [
            state.event_cost.gather(
                1, torch.as_tensor(state.keep[state.labels], device=events.xy.device)[:, None]
            )
            for state in states
        ]
        # Discovery groups events on the CPU: the one copy back, for all windows.
        own = nn.utils.rnn.pad_sequence(own, batch_first=True)[..., 0].cpu().numpy()
        candidates = []
        for row, state in enumerate(states):
            regions = candidate_regions(
                state.xy,
                state.labels,
                own[row, : len(state.events)],
                self.sensor_size,
                min_events=self.config.discovery_min_events,
                residual_cost=self.config.discovery_residual_cost,
                radius=self.config.discovery_radius,
            )
            regions = regions[: self.config.discovery_max_proposals]
            candidates.append(self._proposal_starts(state, regions))
            state.regions = [members for _, members in regions]
        counts = [len(candidate.start) for candidate in candidates]
        fitted = [candidate.start for candidate in candidates]
        if any(counts):
            # One pool of proposals per window, padded to the most regions; padding has no events.
            start = events.xy.new_zeros(len(states), max(counts), self.model.n_params)
            members = events.xy.new_zeros(len(states), max(counts), events.t.shape[1])
            for row, candidate in enumerate(candidates):
                start[row, : counts[row]] = candidate.start
                members[row, : counts[row], : candidate.members.shape[1]] = candidate.members
            fitted = self.proposal_fit(events, start, members)
        for row, (state, candidate) in enumerate(zip(states, candidates, strict=True)):
            accepted = self._accepted(candidate, fitted[row][: counts[row]])
            proposed = fitted[row][: counts[row]][accepted]
            state.regions = [
                region for region, keep in zip(state.regions, accepted.tolist(), strict=True) if keep
            ]
            if len(proposed):
                # The proposals are fitted already: the next labelling decides which are used.
                state.proposed_from = state.params.shape[0]
                state.params = torch.cat([state.params, proposed])
                state.rounds_left = max(state.rounds_left, 1) + 1
                state.step = "label"
            else:
                state.step = "stop"

    def _proposal_starts(self, state: _Window, regions: list[tuple[int, np.ndarray]]) -> _Candidates:
        """The regions of one window (:func:`~evseg_torch.level_two.discovery.candidate_regions`) and the
        start of each one's fit."""
        params, device = state.params, state.params.device
        members = params.new_zeros(len(regions), len(state.events))
        if not regions:
            empty = params.new_zeros(0, params.shape[1])
            return _Candidates(members, empty, empty, *gather_members(state.events, members))
        sizes = [len(region) for _, region in regions]
        rows = torch.as_tensor(np.repeat(np.arange(len(regions)), sizes), device=device)
        members[rows, torch.as_tensor(np.concatenate([region for _, region in regions]), device=device)] = 1.0
        members = _subsample(members, _PROPOSAL_MAX_EVENTS)
        origin = params[torch.as_tensor([cluster for cluster, _ in regions], device=device)]
        own, weights = gather_members(state.events, members)
        velocity = centroid_velocity(own, weights)
        translation = translation_params(self.model, own.xy, weights, velocity)
        starts = torch.stack([recentred(self.model, own.xy, weights, origin, velocity), translation])
        with torch.no_grad():
            # Of the two starts, the fit continues from the sharper one: an optimiser's iterations on
            # the other would mostly be spent where the first already is.
            sharper = self._region_loss(own, starts.flatten(0, 1), weights).view(2, -1).argmin(dim=0)
        start = starts[sharper, torch.arange(len(regions), device=device)]
        return _Candidates(members, start, origin, own, weights)

    def _accepted(self, candidate: _Candidates, fitted: Tensor) -> Tensor:
        """Which fitted proposals :math:`(R, P)` of one window sharpen their regions without collapse,
        bool :math:`(R,)`."""
        if not len(fitted):
            return torch.zeros(0, dtype=torch.bool, device=fitted.device)
        with torch.no_grad():
            losses = self._region_loss(
                candidate.own, torch.cat([candidate.origin, fitted]), candidate.weights
            )
            losses = losses.view(2, -1)
            # A proposal that compensates its region less sharply than the region's own model is none.
            keep = losses[1] <= (1.0 + self.config.discovery_min_gain) * losses[0]
            # Event collapse (reference §5): a fit that shrinks or swells its region's area by more than
            # _MAX_AREA_CHANGE on average has piled events up, not found a motion.
            weights = candidate.weights
            area = (warp_area_element(self.model, candidate.own, fitted) * weights).sum(dim=1) / weights.sum(
                dim=1
            )
            keep &= (area - 1.0).abs() <= _MAX_AREA_CHANGE
        return keep

    def _compensated(self, state: _Window) -> np.ndarray:
        """Every event of the window compensated by every model of its pool, :math:`(K, N, 2)`, on the CPU."""
        with torch.no_grad():
            return warp_events(self.model, state.events.xy, state.events.t, state.params).cpu().numpy()

    def _object_groups(self, state: _Window, warped: np.ndarray) -> dict[int, tuple[np.ndarray, int]]:
        """:func:`~evseg_torch.level_two.objects.cluster_groups` of the window's labelled clusters."""
        return cluster_groups(
            warped[: state.params.shape[0] - len(state.regions)],
            state.labels,
            state.polarity,
            state.xy,
            self.sensor_size,
            radius=self.config.object_radius,
            min_events=self.config.discovery_min_events,
        )

    def _support_cost(self, state: _Window) -> np.ndarray:
        """The support term of every site under every model of the window, :math:`(S, K)`
        (:func:`~evseg_torch.level_two.objects.support_cost`; a proposal's support is its region)."""
        warped = self._compensated(state)
        per_event = support_cost(
            warped,
            self._object_groups(state, warped),
            state.labels,
            state.regions,
            self.sensor_size,
            cost=self.config.lambda_data * self.config.object_support_cost,
            radius=self.config.object_support_radius,
        )
        site_cost = np.zeros((state.n_sites, per_event.shape[1]))
        for model in np.flatnonzero(per_event.any(axis=0)):
            site_cost[:, model] = np.bincount(
                state.sites, weights=per_event[:, model], minlength=state.n_sites
            )
        return site_cost

    def _split(self, state: _Window) -> bool:
        """Split the window's clusters of separate objects, each part keeping its parent's model until its
        refit (:func:`~evseg_torch.level_two.objects.split_objects`); whether any cluster was split."""
        labels, parent = split_objects(state.labels, self._object_groups(state, self._compensated(state)))
        if len(parent) == state.params.shape[0]:
            return False
        state.labels = labels
        state.node_labels = _site_majority(labels, state.sites, state.n_sites)
        state.params = state.params[torch.as_tensor(parent, device=state.params.device)]
        return True

    def _region_loss(self, events: EventBatch, params: Tensor, weights: Tensor) -> Tensor:
        """Contrast loss of ``params`` (two rows per region) on the gathered regions' events."""
        return contrast_loss(
            self.model,
            EventBatch(events.xy.repeat(2, 1, 1), events.t.repeat(2, 1), events.p.repeat(2, 1)),
            params,
            weights.repeat(2, 1),
            sensor_size=self.sensor_size,
            objective=self.config.objective,
            sigma=self.config.sigma,
            collapse_weight=self.config.collapse_weight,
        )

    def _refit(self, refit: ContrastMaximization, events: EventBatch, states: list[_Window]) -> None:
        """Refit every cluster of the windows by contrast maximisation of its own events, all at once."""
        params, _ = _padded_pools([state.params for state in states])
        labels = _padded_rows([state.labels for state in states], events.t.shape[1], device=events.xy.device)
        members = _members(labels, params.shape[1], params.dtype)
        if self.config.refit_max_events is not None:
            members = _subsample(members, self.config.refit_max_events)
        with torch.enable_grad():
            fitted = refit(events, params, members).detach()
        for row, state in enumerate(states):
            state.params = fitted[row, : state.params.shape[0]]

    def _results(self, batch: EventBatch, states: list[_Window]) -> list[LevelTwoResult]:
        """Each window's result; the images of all windows come from one splat."""
        device = batch.xy.device
        labels = _padded_rows([state.labels for state in states], batch.t.shape[1], device=device)
        params, _ = _padded_pools([state.params for state in states])
        members = _members(labels, params.shape[1], params.dtype)
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

    def _label_cost(self, n_events: int) -> float:
        """The label cost of a window of ``n_events``: ``lambda_label``, times
        ``n_events / label_cost_events`` in windows of more than ``label_cost_events`` events."""
        if self.config.label_cost_events is None:
            return self.config.lambda_label
        return self.config.lambda_label * max(1.0, n_events / self.config.label_cost_events)

    def _check_params(self, params, events: EventBatch) -> Tensor:
        if not isinstance(params, Tensor):
            raise ShapeError(f"init_params must be a torch.Tensor (K, P), got {type(params).__name__}")
        if params.ndim != 2 or params.shape[0] == 0 or params.shape[1] != self.model.n_params:
            raise ShapeError(
                f"init_params must be (K, {self.model.n_params}) with K >= 1 for the {self.model.name} "
                f"model, got {tuple(params.shape)}"
            )
        if not torch.isfinite(params).all():
            raise ModelError("init_params hold NaN or inf: every model's parameters must be finite")
        return params.detach().to(device=events.xy.device, dtype=events.xy.dtype).clone()

    @staticmethod
    def _check_labels(labels, events: EventBatch, params: Tensor) -> Tensor:
        labels = torch.as_tensor(labels, device=events.xy.device)
        if labels.shape != (len(events),) or labels.dtype.is_floating_point or labels.dtype == torch.bool:
            raise ShapeError(
                f"labels must be integers of shape ({len(events)},), got {labels.dtype} {tuple(labels.shape)}"
            )
        if len(labels) and (labels.min() < 0 or labels.max() >= params.shape[0]):
            raise ShapeError(
                f"labels must lie in [0, {params.shape[0]}) to index the {params.shape[0]} models"
            )
        return labels.long()


def _renumber_by_size(labels: np.ndarray, n_labels: int) -> tuple[np.ndarray, np.ndarray]:
    """Renumbering that drops empty labels and orders the rest by decreasing size (ties by index).

    Returns the new index of every old label (-1 if dropped) and, for each new label, its old index.
    """
    counts = np.bincount(labels, minlength=n_labels)
    order = np.argsort(-counts, kind="stable")
    keep = order[counts[order] > 0]
    mapping = np.full(n_labels, -1, dtype=np.int64)
    mapping[keep] = np.arange(keep.shape[0])
    return mapping, keep


def _site_majority(labels: np.ndarray, sites: np.ndarray, n_sites: int) -> np.ndarray:
    """The most frequent label of each site's events (ties to the lower label)."""
    n_labels = int(labels.max()) + 1
    votes = np.bincount(sites * n_labels + labels, minlength=n_sites * n_labels)
    return votes.reshape(n_sites, n_labels).argmax(axis=1)


def _changed(old: np.ndarray, new: np.ndarray, keep: np.ndarray) -> float:
    """Fraction of events whose model changed; ``new`` numbers the surviving models ``keep`` of ``old``'s."""
    return float(np.mean(keep[new] != old))


def _members(labels: Tensor, n_clusters: int, dtype: torch.dtype) -> Tensor:
    """One-hot memberships :math:`(..., K, N)` of labels :math:`(..., N)`; label -1 (padding) is in none."""
    return (labels[..., None, :] == torch.arange(n_clusters, device=labels.device)[:, None]).to(dtype)


def _subsample(weights: Tensor, max_events: int) -> Tensor:
    """Keep every s-th member of each cluster (in event order), s chosen so that at most ``max_events`` stay.

    Args:
        weights: one-hot memberships :math:`(..., K, N)`.
    """
    counts = weights.sum(dim=-1, keepdim=True)
    stride = torch.ceil(counts / max_events).clamp_min(1)
    rank = torch.cumsum(weights, dim=-1) - 1
    return weights * (torch.remainder(rank, stride) == 0)


def _chunks(sizes: Sequence[int], budget: int | None) -> list[list[int]]:
    """Consecutive indices of ``sizes`` in chunks whose sizes add up to at most ``budget`` (each chunk
    holds one at least); one chunk of all for ``budget`` ``None``."""
    chunks, total = [[]], 0
    for index, size in enumerate(sizes):
        total += size
        if chunks[-1] and budget is not None and total > budget:
            chunks.append([])
            total = size
        chunks[-1].append(index)
    return chunks


def _select(batch: EventBatch, states: Sequence[_Window]) -> EventBatch:
    """The windows of ``states`` from the padded batch (itself when it holds just them), padded to the
    longest of them."""
    rows = [state.index for state in states]
    if rows == list(range(len(batch))):
        return batch
    index = torch.as_tensor(rows, device=batch.xy.device)
    longest = max(len(state.events) for state in states)
    xy, t, p, lengths = (field[index] for field in batch)
    return EventBatch(xy[:, :longest], t[:, :longest], p[:, :longest], lengths)


def _padded_rows(rows: Sequence[np.ndarray], length: int, device: torch.device) -> Tensor:
    """Integer rows :math:`(n_b,)` as one int64 tensor :math:`(B, L)`, ``L = length``, padded with -1,
    moved to ``device`` in one copy."""
    padded = np.full((len(rows), length), -1, dtype=np.int64)
    for index, row in enumerate(rows):
        padded[index, : len(row)] = row
    return torch.as_tensor(padded, device=device)


def _padded_pools(pools: Sequence[Tensor]) -> tuple[Tensor, Tensor]:
    """Pools :math:`(K_b, P)` as one tensor :math:`(B, K, P)` padded with zeros, and which models are
    real, bool :math:`(B, K)`."""
    params = nn.utils.rnn.pad_sequence(list(pools), batch_first=True)
    counts = torch.tensor([len(pool) for pool in pools], device=params.device)
    return params, torch.arange(params.shape[1], device=params.device) < counts[:, None]

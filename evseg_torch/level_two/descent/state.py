"""One window's state in level two's descent, and the only code that changes it.

:class:`WindowState` (begun by :func:`start_window`) holds a window's graph, its pool, labels and costs,
its budgets of rounds, discovery rounds and splits, and the last step with its outcome, which
:func:`~evseg_torch.level_two.descent.steps.next_step` reads. The steps themselves compute (the
labelling, the refits, discovery's proposals, the object phase's support term and splits) and hand
their results to the window's methods, which are the only writers of its state.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from evseg_torch.config import LevelTwoConfig
from evseg_torch.events import EventBatch
from evseg_torch.graphcut.problem import PottsGraph, potts_graph
from evseg_torch.level_two.checks import check_labels, check_params
from evseg_torch.level_two.descent.steps import Step
from evseg_torch.level_two.energy.graph import event_graph, site_graph
from evseg_torch.motion import MotionModel

__all__ = ["WindowState", "changed_fraction", "renumber_by_size", "site_majority", "start_window"]


@dataclass
class WindowState:
    """One window in level two's descent (module docstring).

    The window: ``index`` in its batch, its ``events``, their integer pixels ``xy`` and ``polarity`` on
    the CPU, the graph cut's ``graph`` over ``n_sites`` nodes and each event's node ``sites`` (the event
    itself without sites).

    The descent: the pool ``params`` :math:`(K, P)`, each event's and node's label (``labels``,
    ``node_labels``; ``None`` before the first labelling), the survivors ``keep`` of the last
    labelling's pool, the energy after each labelling ``history``, the last data costs ``event_cost``
    :math:`(N, K)` and their sums per node ``node_cost`` for the graph cut (``costs_ready`` when they are
    set for the next labelling already), and the budgets ``rounds_left``, ``discoveries_left`` and
    ``splits_left``; ``carried`` when the pool is models a stream carried in.

    Discovery: the events of each proposal ``regions`` (its first support in the object phase), the
    pool index ``proposed_from`` of the first proposal awaiting a labelling, and ``new_clusters``, the
    clusters the last round's proposals became (``None`` until a round's proposals are labelled), the
    only ones a later round proposes from. ``objects_on`` once the object phase has begun.

    The last step ``last`` and its outcome: ``settled`` (a labelling converged or used the last round),
    ``proposed`` (discovery proposed models), ``outside_support`` (the support term put some node
    outside its own cluster's support), ``split_made``; ``step``, the step it takes next.
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
    carried: bool = False
    history: list[float] = field(default_factory=list)
    keep: np.ndarray | None = None
    event_cost: Tensor | None = None
    node_cost: np.ndarray | None = None
    costs_ready: bool = False
    regions: list[np.ndarray] = field(default_factory=list)
    proposed_from: int | None = None
    new_clusters: np.ndarray | None = None
    objects_on: bool = False
    last: Step | None = None
    settled: bool = False
    proposed: bool = False
    outside_support: bool = False
    split_made: bool = False
    step: Step = Step.LABEL

    def costed(self, event_cost: Tensor, node_cost: np.ndarray) -> None:
        """The data costs :math:`(N, K)` of the window's events and their sums per node, for the next
        labelling."""
        self.event_cost, self.node_cost = event_cost, node_cost

    def labelled(
        self, node_labels: np.ndarray, energy: float, label_tol: float, settle_on_reject: bool = False
    ) -> None:
        """A labelling of the nodes and its energy: empty models dropped, the others renumbered by size
        (largest first), and whether the labels settled (one model left, the energy unchanged, or at
        most ``label_tol`` of the events relabelled; or no round left; or, with ``settle_on_reject``,
        every proposal of the round rejected)."""
        self.rounds_left -= 1
        event_labels = node_labels[self.sites]
        mapping, keep = renumber_by_size(event_labels, self.params.shape[0])
        self.node_labels, labels = mapping[node_labels], mapping[event_labels]
        self.params = self.params[torch.as_tensor(keep, device=self.params.device)]
        converged = (
            len(keep) == 1
            or (bool(self.history) and energy == self.history[-1])
            or (self.labels is not None and changed_fraction(self.labels, labels, keep) <= label_tol)
        )
        if self.proposed_from is not None:
            self.new_clusters = keep >= self.proposed_from
            if not self.new_clusters.any():
                self.discoveries_left = 0  # every proposal was rejected: proposing again would repeat them
                converged = converged or settle_on_reject
        elif self.new_clusters is not None and not self.objects_on:
            # Followed through the descent's renumbering; the object phase, whose splits add clusters,
            # comes after the last round and no longer needs it.
            self.new_clusters = self.new_clusters[keep]
        self.proposed_from = None
        self.regions = []
        self.labels, self.keep = labels, keep
        self.history.append(energy)
        self.costs_ready = False
        self.settled = converged or self.rounds_left == 0
        self.last = Step.LABEL

    def refitted(self, params: Tensor) -> None:
        """The clusters' refitted models :math:`(K, P)`."""
        self.params = params
        self.last = Step.REFIT

    def add_proposals(self, params: Tensor, regions: list[np.ndarray]) -> None:
        """Discovery's fitted proposals :math:`(R, P)` and their regions' events: the next labelling
        decides which are used. The first round's are labelled, refitted to the events they got and
        labelled again; a later round's are labelled once (:mod:`~evseg_torch.level_two.discovery`)."""
        self.discoveries_left -= 1
        self.regions = regions
        self.proposed = len(params) > 0
        if self.proposed:
            self.proposed_from = self.params.shape[0]
            self.params = torch.cat([self.params, params])
            self.rounds_left = max(self.rounds_left, 1) + (self.new_clusters is None)
        self.last = Step.PROPOSE

    def add_support(self, support: np.ndarray) -> None:
        """The object phase's support term of every node under every model :math:`(S, K)`: it joins the
        data costs, and a labelling follows where some node lies outside its own cluster's support. No
        model moved since the last labelling, so its data costs stand for the surviving models."""
        self.objects_on = True
        self.outside_support = bool(np.any(support[np.arange(self.n_sites), self.node_labels] > 0))
        if self.outside_support:
            self.event_cost = self.event_cost[:, torch.as_tensor(self.keep, device=self.params.device)]
            self.node_cost = self.node_cost[:, self.keep] + support
            self.costs_ready = True
            self.rounds_left = max(self.rounds_left, 1)
        self.last = Step.SUPPORT

    def split_into(self, split: tuple[np.ndarray, np.ndarray] | None) -> None:
        """The object phase's split (:func:`~evseg_torch.level_two.objects.split_objects`): the new labels
        and each new cluster's parent, whose model it keeps until its refit; ``None`` where no cluster
        holds separate objects."""
        self.split_made = split is not None
        if split is not None:
            labels, parent = split
            self.labels = labels
            self.node_labels = site_majority(labels, self.sites, self.n_sites)
            self.params = self.params[torch.as_tensor(parent, device=self.params.device)]
            self.splits_left -= 1
            self.rounds_left = max(self.rounds_left, 1)
        self.last = Step.SPLIT


def start_window(
    index: int,
    events: EventBatch,
    init_params: Tensor,
    init_labels,
    model: MotionModel,
    sensor_size: tuple[int, int],
    config: LevelTwoConfig,
    discovery_rounds: int,
    carried: bool = False,
) -> WindowState:
    """A window's graph (:mod:`~evseg_torch.level_two.energy.graph`) and starting point, its inputs
    checked."""
    params = check_params(init_params, events, model)
    labels = None if init_labels is None else check_labels(init_labels, events, params).cpu().numpy()
    if config.site_time_slices is None:
        edges, weights = event_graph(events, sensor_size=sensor_size, temporal_edges=config.temporal_edges)
        sites = np.arange(len(events))
    else:
        sites, edges, weights = site_graph(
            events,
            sensor_size=sensor_size,
            time_slices=config.site_time_slices,
            temporal_edges=config.temporal_edges,
        )
    n_sites = int(sites.max()) + 1
    rounds = config.carried_rounds if carried and config.carried_rounds else config.n_iter_segmentation
    # Sites are numbered in row-major pixel order, already local; events are in time order.
    graph = potts_graph(edges, weights, n_nodes=n_sites, reorder=config.site_time_slices is None)
    node_labels = labels
    if labels is not None and config.site_time_slices is not None:
        node_labels = site_majority(labels, sites, n_sites)
    return WindowState(
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
        rounds_left=rounds,
        discoveries_left=discovery_rounds,
        splits_left=config.object_splits,
        carried=carried,
    )


def renumber_by_size(labels: np.ndarray, n_labels: int) -> tuple[np.ndarray, np.ndarray]:
    """Renumbering that drops empty labels and orders the rest by decreasing size (ties by index).

    Returns the new index of every old label (-1 if dropped) and, for each new label, its old index.
    """
    counts = np.bincount(labels, minlength=n_labels)
    order = np.argsort(-counts, kind="stable")
    keep = order[counts[order] > 0]
    mapping = np.full(n_labels, -1, dtype=np.int64)
    mapping[keep] = np.arange(keep.shape[0])
    return mapping, keep


def site_majority(labels: np.ndarray, sites: np.ndarray, n_sites: int) -> np.ndarray:
    """The most frequent label of each site's events (ties to the lower label)."""
    n_labels = int(labels.max()) + 1
    votes = np.bincount(sites * n_labels + labels, minlength=n_sites * n_labels)
    return votes.reshape(n_sites, n_labels).argmax(axis=1)


def changed_fraction(old: np.ndarray, new: np.ndarray, keep: np.ndarray) -> float:
    """Fraction of events whose model changed; ``new`` numbers the surviving models ``keep`` of ``old``'s."""
    return float(np.mean(keep[new] != old))

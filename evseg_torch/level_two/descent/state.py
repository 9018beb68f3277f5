"""One window's state in level two's block-coordinate descent, and the helpers that batch windows.

:class:`WindowState` (started by :func:`start_window`) is what the segmenter
(:mod:`~evseg_torch.level_two.descent.segmenter`), discovery (:mod:`~evseg_torch.level_two.discovery`) and the
object phase (:mod:`~evseg_torch.level_two.objects`) step, round by round; :class:`StageClock` times the
stages; the functions below renumber labels, build memberships and pad the windows of a batch into shared
tensors.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum

import numpy as np
import torch
from torch import Tensor, nn

from evseg_torch.config import LevelTwoConfig
from evseg_torch.events import EventBatch
from evseg_torch.graphcut.alpha_expansion import PottsGraph, potts_graph
from evseg_torch.level_two.checks import check_labels, check_params
from evseg_torch.level_two.energy.graph import event_graph, site_graph
from evseg_torch.motion import MotionModel


class Step(Enum):
    """What a window does next in level two's block-coordinate descent."""

    LABEL = "label"  # label again (with new proposals, or the object phase's support term)
    REFIT = "refit"  # refit every cluster's model to its events, then label
    PROPOSE = "propose"  # discovery: propose models for candidate regions, then label
    STOP = "stop"  # the window is done


@dataclass
class WindowState:
    """One window's block-coordinate descent as the segmenter steps it, round by round.

    ``sites`` maps each event to its graph-cut node (the event itself without sites), ``xy`` holds its
    integer pixels on the CPU (for discovery), ``event_cost`` the last data costs :math:`(N, K)` and
    ``node_cost`` their sums per node for the graph cut (``costs_ready`` when they are set for the next
    labelling already); ``step`` (:class:`Step`) is what follows the last labelling.
    ``objects_on`` once the object phase has begun, ``splits_left`` its splits still allowed, ``regions``
    the events of each proposal (its first support); ``new_clusters`` marks the clusters that the last
    discovery round's proposals became (``None`` until a round's proposals are labelled), the only ones a
    later round proposes from.
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
    new_clusters: np.ndarray | None = None
    event_cost: Tensor | None = None
    node_cost: np.ndarray | None = None
    keep: np.ndarray | None = None
    step: Step = Step.LABEL


STAGES = ("graph", "data_term", "labelling", "refit", "discovery", "images")
"""The stages of level two that :class:`StageClock` times."""


class StageClock:
    """Wall-clock milliseconds per stage and window; a stage run for several windows at once is shared
    evenly by them, so the windows' timings add up to the batch's."""

    def __init__(self, n_windows: int) -> None:
        self.timings = [dict.fromkeys(STAGES, 0.0) for _ in range(n_windows)]
        self._last = time.perf_counter()

    def lap(self, stage: str, windows: Sequence[WindowState]) -> None:
        now = time.perf_counter()
        share = 1e3 * (now - self._last) / len(windows)
        for window in windows:
            self.timings[window.index][stage] += share
        self._last = now


def start_window(
    index: int,
    events: EventBatch,
    init_params: Tensor,
    init_labels,
    model: MotionModel,
    sensor_size: tuple[int, int],
    config: LevelTwoConfig,
    discovery_rounds: int,
) -> WindowState:
    """A window's graph (:mod:`~evseg_torch.level_two.energy.graph`) and starting point, its inputs checked."""
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
        rounds_left=config.n_iter_segmentation,
        discoveries_left=discovery_rounds,
        splits_left=config.object_splits,
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


def memberships(labels: Tensor, n_clusters: int, dtype: torch.dtype) -> Tensor:
    """One-hot memberships :math:`(..., K, N)` of labels :math:`(..., N)`; label -1 (padding) is in none."""
    return (labels[..., None, :] == torch.arange(n_clusters, device=labels.device)[:, None]).to(dtype)


def subsample(weights: Tensor, max_events: int) -> Tensor:
    """Keep every s-th member of each cluster (in event order), s chosen so that at most ``max_events`` stay.

    Args:
        weights: one-hot memberships :math:`(..., K, N)`.
    """
    counts = weights.sum(dim=-1, keepdim=True)
    stride = torch.ceil(counts / max_events).clamp_min(1)
    rank = torch.cumsum(weights, dim=-1) - 1
    return weights * (torch.remainder(rank, stride) == 0)


def chunks(sizes: Sequence[int], budget: int | None) -> list[list[int]]:
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


def select_windows(batch: EventBatch, states: Sequence[WindowState]) -> EventBatch:
    """The windows of ``states`` from the padded batch (itself when it holds just them), padded to the
    longest of them."""
    rows = [state.index for state in states]
    if rows == list(range(len(batch))):
        return batch
    index = torch.as_tensor(rows, device=batch.xy.device)
    longest = max(len(state.events) for state in states)
    xy, t, p, lengths = (field[index] for field in batch)
    return EventBatch(xy[:, :longest], t[:, :longest], p[:, :longest], lengths)


def padded_rows(rows: Sequence[np.ndarray], length: int, device: torch.device) -> Tensor:
    """Integer rows :math:`(n_b,)` as one int64 tensor :math:`(B, L)`, ``L = length``, padded with -1,
    moved to ``device`` in one copy."""
    padded = np.full((len(rows), length), -1, dtype=np.int64)
    for index, row in enumerate(rows):
        padded[index, : len(row)] = row
    return torch.as_tensor(padded, device=device)


def padded_pools(pools: Sequence[Tensor]) -> tuple[Tensor, Tensor]:
    """Pools :math:`(K_b, P)` as one tensor :math:`(B, K, P)` padded with zeros, and which models are
    real, bool :math:`(B, K)`."""
    params = nn.utils.rnn.pad_sequence(list(pools), batch_first=True)
    counts = torch.tensor([len(pool) for pool in pools], device=params.device)
    return params, torch.arange(params.shape[1], device=params.device) < counts[:, None]

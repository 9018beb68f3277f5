r"""Discovery (beyond the paper): regions of events that may follow a motion missing from the pool.

The paper's level two (EMSGC's descent) can only remove models, so a motion that level one missed, or
merged with another, is never recovered. Discovery proposes models from a settled labelling; the next
labelling, with its label cost, decides whether each is used. Regions are spatially connected groups of
events on the pixel grid (each event's pixel dilated by ``radius``, so events of one sparse, fast object
a few pixels apart join one group while separate objects stay apart), of three kinds:

* **split**: a cluster whose events form two or more separate groups of at least ``min_events`` each
  (two objects that one compromise model holds, or an object and a patch of background) proposes each
  group; a cluster of one group other than the largest proposes its two halves across its principal
  axis (:func:`bisect`): two touching objects held by one compromise model are each compensated more
  sharply by a model of their own;
* **merge**: two touching clusters other than the largest (an object that a poor model split in two)
  propose their union;
* **residual**: events that their own model compensates badly (data cost at least ``residual_cost``: a
  motion-blurred streak) are grouped, and each group of at least ``min_events`` is proposed.

A later round (``discovery_rounds`` above 1) proposes only the regions that hold events of a cluster the
round before created (a new cluster's halves and groups, its unions with its neighbours); elsewhere the
labelling is one whose proposals were judged already. A later round's accepted proposals are labelled
once, the first round's labelled, refitted and labelled again.

Each region is fitted by contrast maximisation of an even subsample of its events from the sharper of two
starts: a pure translation at the velocity of the region's event centroid (the least-squares slope of
the events' positions over time, which a small object's streak follows closely whatever the pool says),
and the model of the cluster it came from moved to that velocity, its rotation and scale kept
(:func:`recentred`). A fit is kept if it compensates its region at least as sharply as the region's own
model and does not collapse it (its area changes by at most a tenth on average).

The background's largest region is fitted only if one of its starts already compensates it more sharply
than the background's model: otherwise its fit returns to that model, which the descent's refit gives
anyway, at the cost of a fit on the whole sensor; where one does, it is a motion hidden in the
background (an object level one missed), and its fit is how it is found.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np
import torch
from torch import Tensor, nn

from evseg_torch.config import LevelTwoConfig
from evseg_torch.events import EventBatch
from evseg_torch.level_two.descent.batches import subsample
from evseg_torch.level_two.descent.state import WindowState
from evseg_torch.level_two.objectives.contrast import warp_area_element
from evseg_torch.level_two.solver.cmax import ContrastMaximization
from evseg_torch.level_two.solver.crops import gather_members
from evseg_torch.motion import MotionModel

__all__ = [
    "Discovery",
    "Proposals",
    "bisect",
    "candidate_regions",
    "centroid_velocity",
    "recentred",
    "translation_params",
]

# A proposal only needs to show whether a region has a sharper motion of its own; an even subsample of
# this many events per region finds it, at a fraction of the cost of fitting whole regions.
_PROPOSAL_MAX_EVENTS = 1500
# Largest mean change of its region's area (the warp's area element) a proposal may make.
_MAX_AREA_CHANGE = 0.1


def candidate_regions(
    xy: np.ndarray,
    labels: np.ndarray,
    own_cost: np.ndarray,
    sensor_size: tuple[int, int],
    *,
    min_events: int,
    residual_cost: float | None,
    radius: int,
    around: np.ndarray | None = None,
    carried: bool = False,
) -> list[tuple[int, np.ndarray]]:
    """Regions of events to propose models for (module docstring).

    Args:
        xy: integer pixel of each event :math:`(N, 2)`, ``x`` the column.
        labels: cluster of each event :math:`(N,)` in ``[0, K)``.
        own_cost: data cost of each event under its own cluster's model :math:`(N,)`, in ``[0, 255]``.
        sensor_size: ``(H, W)``.
        min_events: fewest events a region needs.
        residual_cost: events costing at least this under their own model are residual; ``None``
            proposes no residual regions.
        radius: dilation of each event's pixel when joining events into regions.
        around: bool :math:`(K,)`, for a later round: only the regions holding events of these clusters
            (the ones the round before created); ``None`` for all.
        carried: the clusters come from models a stream carried in, whose objects the windows before
            split and joined already: no cluster's halves and no union are proposed again, only the
            separate groups of a cluster (objects that parted, a new object in the background's view)
            and residual regions.

    Returns:
        ``(cluster, members)`` pairs: the cluster a region came from (the larger of a merged pair, the
        majority cluster of a residual region) and the int64 indices of its events, largest regions
        first.
    """
    regions = []
    n_clusters = int(labels.max()) + 1 if len(labels) else 0
    around = np.ones(n_clusters, dtype=bool) if around is None else around
    for cluster in np.flatnonzero(around[:n_clusters]).tolist():
        groups = _connected_groups(xy, labels == cluster, sensor_size, min_events, radius)
        if len(groups) == 1 and carried:
            groups = []
        elif len(groups) == 1:
            # Not the largest cluster: it spans the view (the background), and a model of half of it
            # only overfits that half (measured: it split the background of sparse windows).
            groups = [part for part in bisect(xy, groups[0]) if len(part) >= min_events] if cluster else []
        regions += [(cluster, members) for members in groups]
    for first in range(1, 0 if carried else n_clusters):
        for second in range(first + 1, n_clusters):
            if not (around[first] or around[second]):
                continue
            pair = (labels == first) | (labels == second)
            touching = any(
                len(np.unique(labels[members])) == 2
                for members in _connected_groups(xy, pair, sensor_size, min_events, radius)
            )
            if touching:
                regions.append((first, np.flatnonzero(pair)))
    if residual_cost is not None:
        for members in _connected_groups(xy, own_cost >= residual_cost, sensor_size, min_events, radius):
            if around[labels[members]].any():
                regions.append((int(np.bincount(labels[members]).argmax()), members))
    regions.sort(key=lambda region: -len(region[1]))
    return regions


def _connected_groups(
    xy: np.ndarray, selected: np.ndarray, sensor_size: tuple[int, int], min_events: int, radius: int
) -> list[np.ndarray]:
    """Indices of the selected events in each connected group of at least ``min_events``."""
    if np.count_nonzero(selected) < min_events:
        return []
    height, width = sensor_size
    chosen = np.flatnonzero(selected)
    mask = np.zeros((height, width), dtype=np.uint8)
    mask[xy[chosen, 1], xy[chosen, 0]] = 1
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), dtype=np.uint8)
    n_groups, group_image = cv2.connectedComponents(cv2.dilate(mask, kernel), connectivity=8)
    group = group_image[xy[chosen, 1], xy[chosen, 0]]
    sizes = np.bincount(group, minlength=n_groups)
    order = np.argsort(group, kind="stable")
    bounds = np.concatenate([[0], np.cumsum(sizes)])
    return [chosen[order[bounds[g] : bounds[g + 1]]] for g in range(1, n_groups) if sizes[g] >= min_events]


def bisect(xy: np.ndarray, members: np.ndarray, n_steps: int = 8) -> list[np.ndarray]:
    """Two halves of a group of events, split across its principal axis by 2-means along that axis.

    Args:
        xy: event pixels :math:`(N, 2)`.
        members: indices of the group's events.
        n_steps: Lloyd iterations, starting from the split at the median.

    Returns:
        The indices of the two halves (one may be empty).
    """
    points = xy[members].astype(np.float64)
    centred = points - points.mean(axis=0)
    _, _, axes = np.linalg.svd(centred.T @ centred)
    along = centred @ axes[0]
    cut = float(np.median(along))
    for _ in range(n_steps):
        low, high = along[along <= cut], along[along > cut]
        if not len(low) or not len(high):
            break
        cut = 0.5 * (low.mean() + high.mean())
    return [members[along <= cut], members[along > cut]]


def centroid_velocity(events: EventBatch, weights: Tensor) -> Tensor:
    r"""Least-squares velocity of each weighted event set's centroid over time, px/s.

    Args:
        events: ``xy`` :math:`(N, 2)` and ``t`` :math:`(N,)` shared by every set, or each set's own
            (padded) events ``xy`` :math:`(R, N, 2)`, ``t`` :math:`(R, N)` (see
            :func:`~evseg_torch.level_two.solver.crops.gather_members`).
        weights: non-negative :math:`(R, N)`, one row per set.

    Returns:
        :math:`(R, 2)`; zero for a set whose events all share one time.
    """
    xy, t = _rows(events.xy, weights), _rows(events.t, weights)
    total = weights.sum(dim=1, keepdim=True).clamp_min(1e-12)
    t_mean = (weights * t).sum(dim=1, keepdim=True) / total
    xy_mean = torch.einsum("rn,rnc->rc", weights, xy) / total
    dt = t - t_mean
    spread = (weights * dt**2).sum(dim=1, keepdim=True)
    moment = torch.einsum("rn,rnc->rc", weights * dt, xy) - (weights * dt).sum(dim=1, keepdim=True) * xy_mean
    return torch.where(spread > 0, moment / spread.clamp_min(1e-30), torch.zeros_like(moment))


def translation_params(model: MotionModel, xy: Tensor, weights: Tensor, velocity: Tensor) -> Tensor:
    r"""Parameters of ``model`` closest (least squares) to a uniform velocity over each weighted set.

    For translation and affine4 this is exactly the translation; rotation3d gets its best approximation.

    Args:
        xy: event pixels :math:`(N, 2)` shared by every set, or each set's own :math:`(R, N, 2)`.
        weights: non-negative :math:`(R, N)`.
        velocity: :math:`(R, 2)` px/s.

    Returns:
        :math:`(R, P)`.
    """
    jac = model.jacobian(_rows(xy, weights))  # (R, N, 2, P)
    normal = torch.einsum("rn,rnap,rnaq->rpq", weights, jac, jac)
    rhs = torch.einsum("rn,rnap,ra->rp", weights, jac, velocity)
    ridge = 1e-9 * normal.diagonal(dim1=1, dim2=2).amax(dim=1).clamp_min(1e-12)
    eye = torch.eye(normal.shape[-1], dtype=normal.dtype, device=normal.device)
    return torch.linalg.solve(normal + ridge[:, None, None] * eye, rhs[..., None])[..., 0]


def recentred(model: MotionModel, xy: Tensor, weights: Tensor, params: Tensor, velocity: Tensor) -> Tensor:
    r"""Models moved so that each weighted set's mean velocity is ``velocity``, their rotation and scale kept.

    ``params`` plus the :func:`translation_params` of the difference between ``velocity`` and the set's
    mean velocity under ``params``: a cluster's model carried over to a part of it that moves otherwise.

    Args:
        xy: event pixels :math:`(N, 2)` shared by every set, or each set's own :math:`(R, N, 2)`.
        weights: non-negative :math:`(R, N)`.
        params: :math:`(R, P)`.
        velocity: :math:`(R, 2)` px/s.

    Returns:
        :math:`(R, P)`.
    """
    total = weights.sum(dim=1, keepdim=True).clamp_min(1e-12)
    jac = model.jacobian(_rows(xy, weights))  # (R, N, 2, P)
    mean_velocity = torch.einsum("rn,rnap,rp->ra", weights, jac, params) / total
    return params + translation_params(model, xy, weights, velocity - mean_velocity)


def _rows(value: Tensor, weights: Tensor) -> Tensor:
    """``value`` with one row per set: shared values :math:`(N, ...)` are broadcast (a view) to R rows."""
    if value.shape[:2] == weights.shape:
        return value
    return value.expand(weights.shape[0], *value.shape)


class Proposals(NamedTuple):
    """One window's accepted proposals: their fitted models :math:`(R, P)` and the events of each one's
    region, the proposal's first support in the object phase."""

    params: Tensor
    regions: list[np.ndarray]


class _Candidates(NamedTuple):
    """One window's candidate regions for discovery: their members :math:`(R, N)` (an even subsample),
    the start of each one's fit :math:`(R, P)`, the contrast loss of the model of the cluster it came
    from on it :math:`(R,)`, and its gathered events and weights :math:`(R, n)`."""

    members: Tensor
    start: Tensor
    origin_loss: Tensor
    own: EventBatch
    weights: Tensor


class Discovery:
    """Level two's discovery step (module docstring): propose models for the candidate regions of the
    windows whose descent has settled.

    Args:
        model: the motion model.
        sensor_size: ``(H, W)``.
        config: level two's settings (``discovery_*``, the refits' objective, blur and collapse guard).
        fit: the contrast maximisation of the proposals (run for ``discovery_max_iter`` iterations).
    """

    def __init__(
        self,
        model: MotionModel,
        sensor_size: tuple[int, int],
        config: LevelTwoConfig,
        fit: ContrastMaximization,
    ) -> None:
        self.model, self.sensor_size, self.config, self.fit = model, sensor_size, config, fit

    def propose(self, events: EventBatch, states: list[WindowState]) -> list[Proposals]:
        """Models for the windows' candidate regions, each window's :class:`Proposals`.

        The regions and the fits' starts are found per window (NumPy and a few small tensor operations);
        the fits, most of discovery's time, run for all windows at once.

        Args:
            events: the windows' events, a padded batch in the order of ``states``.
            states: the windows, each right after a settled labelling (read, not changed).
        """
        own = [
            state.event_cost.gather(
                1, torch.as_tensor(state.keep[state.labels], device=events.xy.device)[:, None]
            )
            for state in states
        ]
        # Discovery groups events on the CPU: the one copy back, for all windows.
        own = nn.utils.rnn.pad_sequence(own, batch_first=True)[..., 0].cpu().numpy()
        candidates, regions_of = [], []
        for row, state in enumerate(states):
            regions = candidate_regions(
                state.xy,
                state.labels,
                own[row, : len(state.events)],
                self.sensor_size,
                min_events=self.config.discovery_min_events,
                residual_cost=self.config.discovery_residual_cost,
                radius=self.config.discovery_radius,
                around=state.new_clusters,
                carried=state.carried and self.config.carried_discovery == "new",
            )
            candidate, regions = self._proposal_starts(state, regions[: self.config.discovery_max_proposals])
            candidates.append(candidate)
            regions_of.append([members for _, members in regions])
        counts = [len(candidate.start) for candidate in candidates]
        fitted = [candidate.start for candidate in candidates]
        if any(counts):
            # One pool of proposals per window, padded to the most regions; padding has no events.
            start = events.xy.new_zeros(len(states), max(counts), self.model.n_params)
            members = events.xy.new_zeros(len(states), max(counts), events.t.shape[1])
            for row, candidate in enumerate(candidates):
                start[row, : counts[row]] = candidate.start
                members[row, : counts[row], : candidate.members.shape[1]] = candidate.members
            fitted = self.fit(events, start, members, max_iter=self.config.discovery_max_iter)
        proposals = []
        for row, (candidate, regions) in enumerate(zip(candidates, regions_of, strict=True)):
            accepted = self._accepted(candidate, fitted[row][: counts[row]])
            kept = [region for region, keep in zip(regions, accepted.tolist(), strict=True) if keep]
            proposals.append(Proposals(fitted[row][: counts[row]][accepted], kept))
        return proposals

    def _proposal_starts(
        self, state: WindowState, regions: list[tuple[int, np.ndarray]]
    ) -> tuple[_Candidates, list[tuple[int, np.ndarray]]]:
        """The regions of one window (:func:`~evseg_torch.level_two.discovery.candidate_regions`) worth a
        fit, and the start of each one's fit.

        The background's largest region is worth one only if a start already compensates it more sharply
        than the background's model: otherwise its fit returns to that model, which the descent's refit
        gives anyway (module docstring)."""
        params, device = state.params, state.params.device
        members = params.new_zeros(len(regions), len(state.events))
        if not regions:
            empty = params.new_zeros(0, params.shape[1])
            return _Candidates(members, empty, empty[:, 0], *gather_members(state.events, members)), regions
        sizes = [len(region) for _, region in regions]
        rows = torch.as_tensor(np.repeat(np.arange(len(regions)), sizes), device=device)
        members[rows, torch.as_tensor(np.concatenate([region for _, region in regions]), device=device)] = 1.0
        members = subsample(members, _PROPOSAL_MAX_EVENTS)
        origin = params[torch.as_tensor([cluster for cluster, _ in regions], device=device)]
        own, weights = gather_members(state.events, members)
        velocity = centroid_velocity(own, weights)
        translation = translation_params(self.model, own.xy, weights, velocity)
        starts = torch.stack([recentred(self.model, own.xy, weights, origin, velocity), translation])
        with torch.no_grad():
            losses = self._region_loss(own, torch.cat([origin, starts.flatten(0, 1)]), weights).view(3, -1)
        # Of the two starts, the fit continues from the sharper one: an optimiser's iterations on the
        # other would mostly be spent where the first already is.
        best, sharper = losses[1:].min(dim=0)
        start = starts[sharper, torch.arange(len(regions), device=device)]
        worth = [True] * len(regions)
        background = [row for row, (cluster, _) in enumerate(regions) if cluster == 0]
        if background:
            main = max(background, key=lambda row: sizes[row])
            worth[main] = bool(best[main] < losses[0, main])
        if all(worth):
            return _Candidates(members, start, losses[0], own, weights), regions
        kept = torch.as_tensor(worth, device=device)
        candidate = _Candidates(
            members[kept],
            start[kept],
            losses[0][kept],
            EventBatch(own.xy[kept], own.t[kept], own.p[kept]),
            weights[kept],
        )
        return candidate, [region for region, keep in zip(regions, worth, strict=True) if keep]

    def _accepted(self, candidate: _Candidates, fitted: Tensor) -> Tensor:
        """Which fitted proposals :math:`(R, P)` of one window sharpen their regions without collapse,
        bool :math:`(R,)`."""
        if not len(fitted):
            return torch.zeros(0, dtype=torch.bool, device=fitted.device)
        with torch.no_grad():
            # A proposal that compensates its region less sharply than the region's own model is none
            # (that model's loss was scored with the starts).
            loss = self._region_loss(candidate.own, fitted, candidate.weights)
            keep = loss <= (1.0 + self.config.discovery_min_gain) * candidate.origin_loss
            # Event collapse (reference §5): a fit that shrinks or swells its region's area by more than
            # _MAX_AREA_CHANGE on average has piled events up, not found a motion.
            weights = candidate.weights
            area = (warp_area_element(self.model, candidate.own, fitted) * weights).sum(dim=1) / weights.sum(
                dim=1
            )
            keep &= (area - 1.0).abs() <= _MAX_AREA_CHANGE
        return keep

    def _region_loss(self, events: EventBatch, params: Tensor, weights: Tensor) -> Tensor:
        """Contrast loss of ``params`` (the same number of rows per region, a block of rows each) on the
        gathered regions' events."""
        repeats = params.shape[0] // weights.shape[0]
        repeated = EventBatch(
            events.xy.repeat(repeats, 1, 1), events.t.repeat(repeats, 1), events.p.repeat(repeats, 1)
        )
        return self.fit.losses(repeated, params, weights.repeat(repeats, 1))

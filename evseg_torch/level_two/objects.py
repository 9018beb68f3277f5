r"""Objects in level two's energy: a cluster is one object, not one motion (beyond the paper).

EMSGC's energy prices a *label*, so one label may cover two separate objects that move alike (its single
label cost is cheaper than two), and may take scattered events far from its object wherever its warp
happens to fit them. Two additions make each non-background cluster one spatially coherent object:

* **support term**: each non-background label :math:`l` has a *support*, the pixels where its own events
  land when compensated by its model: the pixels of its *object groups* (below), dilated by
  ``support_radius``. An event whose position compensated by :math:`\theta_l` falls outside that support
  pays ``support_cost`` more for label :math:`l`. Scattered events far from an object stop joining its
  cluster, and one object's cluster cannot take over another, separate object's events by α-expansion
  (it would pay for every one of them), so two objects that move alike keep two labels. The background
  (the cluster whose events spread widest over the view, :func:`coverage`, whether or not it holds the
  most events: large, densely textured objects can outnumber a sparse background; and any other cluster
  whose events spread over the view: :func:`spans_view`) has no support
  term. The term applies in level two's *object phase*, the labellings after its descent has settled
  (:mod:`~evseg_torch.level_two.descent.steps`; supports built from the first labelling would keep the
  mistakes of its poor early labels). A label's support is rebuilt before each of
  those labellings from the current labels and refitted models; a model proposed by discovery has its
  region as its first support.
* **object split**: when a labelling of the object phase has settled, a non-background cluster whose
  compensated events form two or more object groups is split, one label per group (the parent's model,
  refitted on the group's own events before the next labelling); then the energy decides, with its
  label cost per label, which of the parts are worth their own label.

Object groups: a cluster's compensated events are counted per pixel; pixels with fewer than two events
in their 3×3 neighbourhood (scattered events, not an object's sharp edges) are dropped, the rest are
dilated by ``radius`` and split into 8-connected components, and a component holding at least
``min_events`` events is a group. A group of one polarity (fewer than ``_MIN_POLARITY`` of its events of
the rarer sign) is an edge strip: a textureless object moving over the background fires one sign on
its leading edge and the other on its trailing edge, two strips apart along the motion with few events
between them. Strips are not objects of their own: each joins the nearest group of the cluster that
carries the other sign (both polarities, or a strip of the opposite sign), and a strip left without a
partner stays with the cluster's largest group; so a textureless object stays one cluster, and the strips
of several objects that a spurious model holds are never split into clusters of their own, while two
objects, each carrying both signs, become two.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from evseg_torch.config import LevelTwoConfig
from evseg_torch.level_two.descent.state import WindowState
from evseg_torch.level_two.energy.label_cost import motion_label_costs
from evseg_torch.level_two.image.warp import warp_events
from evseg_torch.motion import MotionModel

__all__ = [
    "ObjectPhase",
    "cluster_groups",
    "coverage",
    "object_groups",
    "spans_view",
    "split_objects",
    "support_cost",
    "support_mask",
]

# Fewest events of the rarer polarity, as a fraction of a group's events, for the group to be an object
# on its own rather than one edge strip of a textureless object.
_MIN_POLARITY = 0.3
# A label's box, for its price: these percentiles of its events' x and y (a few strays do not stretch it).
_BOX_PERCENTILES = (2, 98)
# A background's events, each pixel dilated by _SPREAD_RADIUS, cover at least this fraction of the sensor.
_BACKGROUND_SPREAD, _SPREAD_RADIUS = 0.35, 5


def spans_view(xy: np.ndarray, sensor_size: tuple[int, int]) -> bool:
    """Whether events :math:`(n, 2)` (integer pixels) spread like a background's: their pixels, dilated by
    5 px, cover at least 35% of the sensor (a box would not tell two objects far apart from a background).

    Such a cluster is no object: it gets no support term and is never split, whether or not it is the
    largest (in a sparse window a fast object's model can briefly hold more events than the camera's).
    """
    return coverage(xy, sensor_size) >= _BACKGROUND_SPREAD


def coverage(xy: np.ndarray, sensor_size: tuple[int, int]) -> float:
    """The fraction of the sensor that events :math:`(n, 2)` (integer pixels) cover, each pixel dilated by
    5 px: how far they spread over the view."""
    mask = np.zeros(sensor_size, dtype=np.uint8)
    mask[xy[:, 1], xy[:, 0]] = 1
    return float(_dilate(mask, _SPREAD_RADIUS).mean())


def object_groups(
    warped_xy: np.ndarray, polarity: np.ndarray, sensor_size: tuple[int, int], *, radius: int, min_events: int
) -> tuple[np.ndarray, int]:
    """The object groups of one cluster's compensated events (module docstring).

    Args:
        warped_xy: the cluster's events compensated by its model :math:`(n, 2)`, ``x`` the column.
        polarity: their polarities :math:`(n,)`, positive or not.
        sensor_size: ``(H, W)``; positions outside are read at the nearest border pixel.
        radius: dilation, in pixels, that joins nearby pixels into one component.
        min_events: fewest events of a group.

    Returns:
        ``(group, n_groups)``: each event's group in ``[0, n_groups)``, or -1 for events in no group
        (scattered ones, or in components too small), strips already joined to their partner groups.
    """
    height, width = sensor_size
    group = np.full(len(warped_xy), -1, dtype=np.int64)
    if len(warped_xy) < min_events:
        return group, 0
    col, row = _pixels(warped_xy, sensor_size)
    counts = np.bincount(row * width + col, minlength=height * width).reshape(height, width)
    # Sum over each pixel's 3x3 neighbourhood, borders read as zero.
    dense = cv2.boxFilter(
        counts.astype(np.float32), -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT
    )
    core = ((counts > 0) & (dense >= 2)).astype(np.uint8)
    n_components, component_image = cv2.connectedComponents(_dilate(core, radius), connectivity=8)
    component = np.where(core[row, col] > 0, component_image[row, col], 0)
    sizes = np.bincount(component, minlength=n_components)
    kept = [c for c in range(1, n_components) if sizes[c] >= min_events]
    if not kept:
        return group, 0
    positive = np.bincount(component, weights=(polarity > 0).astype(np.float64), minlength=n_components)
    share = positive[kept] / sizes[kept]
    sign = np.where(share >= 1 - _MIN_POLARITY, 1, np.where(share <= _MIN_POLARITY, -1, 0))
    centre = (
        np.stack(
            [
                np.bincount(component, weights=warped_xy[:, axis], minlength=n_components)[kept]
                for axis in (0, 1)
            ],
            axis=1,
        )
        / sizes[kept, None]
    )
    # Each strip joins the nearest component carrying the other sign; components joined are one group.
    parent = np.arange(len(kept))
    for index in np.flatnonzero(sign != 0):
        partners = np.flatnonzero(sign != sign[index])
        if len(partners):
            nearest = partners[np.argmin(np.linalg.norm(centre[partners] - centre[index], axis=1))]
            _join(parent, index, nearest)
    roots = np.array([_root(parent, index) for index in range(len(kept))])
    # A group still of one sign is a strip without a partner: not an object of its own, it stays with
    # the largest group that carries both signs (or, where there is none, all the groups are one).
    root_positive = np.bincount(roots, weights=positive[kept], minlength=len(kept))
    root_size = np.bincount(roots, weights=sizes[kept], minlength=len(kept))
    both = (root_size > 0) & (np.abs(root_positive / np.maximum(root_size, 1) - 0.5) < 0.5 - _MIN_POLARITY)
    if np.any(both):
        largest = int(np.argmax(np.where(both, root_size, -1)))
        roots = np.where(both[roots], roots, largest)
    else:
        roots = np.zeros_like(roots)
    _, group_of_kept = np.unique(roots, return_inverse=True)
    lookup = np.full(n_components, -1, dtype=np.int64)
    lookup[kept] = group_of_kept
    return lookup[component], int(group_of_kept.max()) + 1


def support_mask(
    warped_xy: np.ndarray, group: np.ndarray, sensor_size: tuple[int, int], *, radius: int
) -> np.ndarray:
    """A cluster's support: the pixels of its grouped compensated events, dilated by ``radius``.

    A cluster without groups (too small to have one) is supported where any of its events land.

    Args:
        warped_xy: the cluster's compensated events :math:`(n, 2)`.
        group: their groups from :func:`object_groups` (-1 for none).
        sensor_size: ``(H, W)``.
        radius: dilation in pixels.

    Returns:
        bool :math:`(H, W)`.
    """
    col, row = _pixels(warped_xy[group >= 0] if np.any(group >= 0) else warped_xy, sensor_size)
    mask = np.zeros(sensor_size, dtype=np.uint8)
    mask[row, col] = 1
    return _dilate(mask, radius).astype(bool)


def cluster_groups(
    warped: np.ndarray,
    labels: np.ndarray,
    polarity: np.ndarray,
    xy: np.ndarray,
    sensor_size: tuple[int, int],
    *,
    radius: int,
    min_events: int,
) -> dict[int, tuple[np.ndarray, int]]:
    """The object groups of every cluster but the background's: the one that spreads widest over the view
    (:func:`coverage`) and any that spans the view.

    Args:
        warped: every event compensated by every cluster's model :math:`(K, N, 2)`.
        labels: cluster of each event :math:`(N,)` in ``[0, K)``.
        polarity: each event's polarity :math:`(N,)`.
        xy: each event's integer pixel :math:`(N, 2)`, for :func:`coverage`.
        sensor_size: ``(H, W)``.
        radius, min_events: as in :func:`object_groups`.

    Returns:
        ``{cluster: (group, n_groups)}`` of :func:`object_groups` for the events ``labels == cluster``
        in index order.
    """
    members_of = [np.flatnonzero(labels == cluster) for cluster in range(len(warped))]
    spread = [coverage(xy[members], sensor_size) for members in members_of]
    background = int(np.argmax(spread))
    groups = {}
    for cluster, members in enumerate(members_of):
        if cluster != background and spread[cluster] < _BACKGROUND_SPREAD:  # not spans_view
            groups[cluster] = object_groups(
                warped[cluster, members], polarity[members], sensor_size, radius=radius, min_events=min_events
            )
    return groups


def support_cost(
    warped: np.ndarray,
    groups: dict[int, tuple[np.ndarray, int]],
    labels: np.ndarray,
    regions: list[np.ndarray],
    sensor_size: tuple[int, int],
    *,
    cost: float,
    radius: int,
) -> np.ndarray:
    """The support term of every event under every model (module docstring).

    Args:
        warped: every event compensated by every model of the pool :math:`(K, N, 2)`: the labelled
            clusters first, then one model per region.
        groups: :func:`cluster_groups` of the labelled clusters; a cluster left out (the background) has
            no support term.
        labels: cluster of each event :math:`(N,)`.
        regions: the events of each model after the labelled clusters (discovery's proposals): its
            support, without groups.
        sensor_size: ``(H, W)``.
        cost: what an event pays for a model whose support its compensated position misses.
        radius: dilation of a support, pixels.

    Returns:
        :math:`(N, K)`, 0 or ``cost``.
    """
    col, row = _pixels(warped, sensor_size)
    n_labelled = len(warped) - len(regions)
    # Each supported model's events and their groups: a cluster's own, a proposal's region (no groups).
    supported = [
        (cluster, np.flatnonzero(labels == cluster), group) for cluster, (group, _) in groups.items()
    ]
    supported += [(n_labelled + k, members, np.full(len(members), -1)) for k, members in enumerate(regions)]
    result = np.zeros((warped.shape[1], len(warped)))
    for model, members, group in supported:
        mask = support_mask(warped[model, members], group, sensor_size, radius=radius)
        result[:, model] = cost * ~mask[row[model], col[model]]
    return result


def split_objects(
    labels: np.ndarray, groups: dict[int, tuple[np.ndarray, int]]
) -> tuple[np.ndarray, np.ndarray]:
    """Split every cluster of two or more object groups into one cluster per group.

    Args:
        labels: cluster of each event :math:`(N,)` in ``[0, K)``.
        groups: for some clusters ``k``, ``(group, n_groups)`` of :func:`object_groups` for the events
            ``labels == k`` in index order.

    Returns:
        ``(labels, parent)``: the new labels (a split cluster keeps its label for its largest group and
        its events in no group; its other groups get new labels ``K, K + 1, ...``) and the cluster each new
        label came from, :math:`(K',)` (``parent[k] = k`` for ``k < K``).
    """
    n_clusters = int(labels.max()) + 1
    labels = labels.copy()
    parent = list(range(n_clusters))
    for cluster, (group, n_groups) in sorted(groups.items()):
        if n_groups < 2:
            continue
        members = np.flatnonzero(labels == cluster)
        largest = np.bincount(group[group >= 0]).argmax()
        for part in range(n_groups):
            if part != largest:
                labels[members[group == part]] = len(parent)
                parent.append(cluster)
    return labels, np.asarray(parent, dtype=np.int64)


def _pixels(xy: np.ndarray, sensor_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The nearest pixel ``(column, row)`` of positions :math:`(..., 2)`, outside ones at the border."""
    height, width = sensor_size
    col = np.clip(np.rint(xy[..., 0]), 0, width - 1).astype(np.int64)
    row = np.clip(np.rint(xy[..., 1]), 0, height - 1).astype(np.int64)
    return col, row


def _dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """``mask`` (uint8) dilated by a square of ``2 radius + 1`` pixels."""
    return cv2.dilate(mask, np.ones((2 * radius + 1, 2 * radius + 1), dtype=np.uint8))


def _root(parent: np.ndarray, index: int) -> int:
    while parent[index] != index:
        index = parent[index]
    return index


def _join(parent: np.ndarray, first: int, second: int) -> None:
    parent[_root(parent, first)] = _root(parent, second)


class ObjectPhase:
    """Level two's object phase (module docstring), stepping a window once its descent has settled.

    Args:
        model: the motion model.
        sensor_size: ``(H, W)``.
        config: level two's settings (``objects``, ``object_*``, ``lambda_data``).
    """

    def __init__(self, model: MotionModel, sensor_size: tuple[int, int], config: LevelTwoConfig) -> None:
        self.model, self.sensor_size, self.config = model, sensor_size, config

    def compensated(self, state: WindowState) -> np.ndarray:
        """Every event of the window compensated by every model of its pool, :math:`(K, N, 2)`, on the CPU."""
        with torch.no_grad():
            return warp_events(self.model, state.events.xy, state.events.t, state.params).cpu().numpy()

    def groups(self, state: WindowState, warped: np.ndarray) -> dict[int, tuple[np.ndarray, int]]:
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

    def support_cost(self, state: WindowState) -> np.ndarray:
        """The support term of every site under every model of the window, :math:`(S, K)`
        (:func:`~evseg_torch.level_two.objects.support_cost`; a proposal's support is its region)."""
        warped = self.compensated(state)
        per_event = support_cost(
            warped,
            self.groups(state, warped),
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

    def split(self, state: WindowState) -> tuple[np.ndarray, np.ndarray] | None:
        """The window's clusters of separate objects split (:func:`split_objects`): the new labels and
        each new cluster's parent; ``None`` where no cluster holds separate objects."""
        labels, parent = split_objects(state.labels, self.groups(state, self.compensated(state)))
        return None if len(parent) == state.params.shape[0] else (labels, parent)

    def label_costs(self, state: WindowState, cost: float) -> dict:
        """The label costs of the window's next labelling, as keyword arguments of
        :func:`~evseg_torch.graphcut.alpha_expansion.alpha_expansion`: ``cost`` per label, or with
        ``object_label_cost`` below 1 a motion priced once for its objects
        (:func:`~evseg_torch.level_two.energy.label_cost.motion_label_costs`; the background is the
        labelled cluster of most events). A label's box spans the 2nd to 98th percentiles of its
        cluster's events, a proposal's of its region's; a label without events has the whole view."""
        if not self.config.objects or self.config.object_label_cost >= 1:
            return {"label_cost": cost}
        n_models = state.params.shape[0]
        n_labelled = n_models - len(state.regions)
        # Before the first labelling no label has events: each then has the whole view.
        labels = np.full(len(state.events), -1) if state.labels is None else state.labels
        members = [np.flatnonzero(labels == k) for k in range(n_labelled)] + list(state.regions)
        height, width = self.sensor_size
        boxes = np.tile([0.0, 0.0, width - 1.0, height - 1.0], (n_models, 1))
        for k, events in enumerate(members):
            if len(events):
                low, high = np.percentile(state.xy[events], _BOX_PERCENTILES, axis=0)
                boxes[k] = [*low, *(high - low)]
        background = int(np.argmax([len(events) for events in members[:n_labelled]]))
        t = state.events.t
        label_cost, label_groups, group_cost = motion_label_costs(
            state.params.detach().cpu().numpy().astype(np.float64),
            boxes,
            background,
            cost,
            self.config.object_label_cost,
            duration=float(t.max() - t.min()) if len(t) else 0.0,
            motion=self.model,
            sensor_size=self.sensor_size,
        )
        return {"label_cost": label_cost, "label_groups": label_groups, "group_cost": group_cost}

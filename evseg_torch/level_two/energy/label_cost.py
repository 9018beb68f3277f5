"""The label cost of a window: EMSGC's MDL term, scaled with dense windows, and priced once per motion
where a cluster is an object (both beyond the paper)."""

from __future__ import annotations

import numpy as np

from evseg_torch.motion.shared import motion_groups, moving_alike

__all__ = ["label_cost", "motion_label_costs"]


def label_cost(n_events: int, lambda_label: float, label_cost_events: float | None) -> float:
    """What each model in use costs a window of ``n_events``: ``lambda_label``, times
    ``n_events / label_cost_events`` in windows of more than ``label_cost_events`` events (``None``:
    ``lambda_label`` whatever the window, as in EMSGC).

    The data cost that a spurious model saves grows with the events it takes, so dense windows need a
    dearer label; sparse ones keep ``lambda_label``, which a small object's sharper model can pay.

    Examples:
        >>> label_cost(5000, 6000.0, 15000.0), label_cost(30000, 6000.0, 15000.0)
        (6000.0, 12000.0)
    """
    if label_cost_events is None:
        return lambda_label
    return lambda_label * max(1.0, n_events / label_cost_events)


def motion_label_costs(
    models: np.ndarray,
    boxes: np.ndarray,
    background: int,
    cost: float,
    object_fraction: float,
    *,
    duration: float,
    motion,
    sensor_size: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A window's label costs where a cluster is an object and a motion is priced once (beyond the paper).

    The labels that share a motion (:func:`~evseg_torch.motion.shared.shared_motion_groups`) form a
    group: the group pays ``(1 - object_fraction) cost`` once when any of them is in use, and each of them
    ``object_fraction cost``; so one object of a motion pays ``cost``, as any label alone does, and each
    further object, a separate object that moves alike, only its fraction. Two labels of one motion
    whose boxes overlap without either holding the other are parts of one object
    (a spinning object's halves, an object cut in two), which two separate objects are not, nor an object
    and the cluster that held it with another: such labels are priced alone, as are the background and
    the labels that move like it.

    Args:
        models: every label's model :math:`(K, P)`.
        boxes: every label's events' box ``[x, y, w, h]`` :math:`(K, 4)`.
        background: the background's label.
        cost: a label's cost (:func:`label_cost`).
        object_fraction: ``level_two.object_label_cost``, in [0, 1].
        duration: the window's time span, seconds.
        motion: the models' :class:`~evseg_torch.motion.MotionModel`.
        sensor_size: ``(H, W)``.

    Returns:
        ``(label_cost, label_groups, group_cost)`` for
        :func:`~evseg_torch.graphcut.alpha_expansion.alpha_expansion`: :math:`(K,)`, int64 :math:`(K,)`
        in ``[-1, G)`` and :math:`(G,)`.
    """
    close = moving_alike(models, boxes, duration, motion, sensor_size)
    shared = motion_groups(close)
    low, high = boxes[:, :2], boxes[:, :2] + boxes[:, 2:]
    meet = np.all((low[:, None] <= high[None]) & (low[None] <= high[:, None]), axis=2)
    holds = np.all((low[:, None] <= low[None]) & (high[None] <= high[:, None]), axis=2)
    parts = meet & ~holds & ~holds.T & (shared[:, None] == shared[None])
    np.fill_diagonal(parts, False)
    objects = np.flatnonzero((shared != shared[background]) & ~parts.any(axis=1))
    # The objects' own groups: those of the moving-alike pairs among them alone.
    own = motion_groups(close[np.ix_(objects, objects)])
    _, index, sizes = np.unique(own, return_inverse=True, return_counts=True)
    grouped = sizes[index] > 1
    group = np.full(len(models), -1, dtype=np.int64)
    _, group[objects[grouped]] = np.unique(own[grouped], return_inverse=True)
    label_costs = np.where(group >= 0, object_fraction * cost, cost)
    return label_costs, group, np.full(int(group.max()) + 1, (1 - object_fraction) * cost)

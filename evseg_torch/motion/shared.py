"""Which clusters share a motion: where a cluster is an object, the objects that move alike.

Two clusters share a motion when their models move the points of the box holding both clusters less
than ``tolerance_px`` (2 px by default) apart over the window: the largest difference at the box's
corners, where a linear velocity field's difference peaks. A group is a connected set of such pairs,
named by its lowest cluster index. Level two prices a motion once and each further object of it a
fraction (:func:`~evseg_torch.level_two.energy.label_cost.motion_label_costs`); the output names the
groups (``shared_motion``).

2 px: the two balls of EED multiple_objects, separate objects thrown together, move 0.4-1.3 px apart
over 30 ms windows (1 px kept one window's balls in one cluster).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse.csgraph import connected_components

__all__ = ["SHARED_MOTION_PX", "motion_groups", "moving_alike", "shared_motion_groups"]

SHARED_MOTION_PX = 2.0  # px over the window: models closer than this share a motion


def shared_motion_groups(
    models, boxes, duration: float, motion, sensor_size, tolerance_px: float = SHARED_MOTION_PX
) -> np.ndarray:
    """Which clusters share a motion (module docstring).

    Args:
        models: :math:`(K, P)`.
        boxes: each cluster's compensated box ``[x, y, w, h]``, :math:`(K, 4)`; a NaN row (no events)
            stands for the whole sensor.
        duration: the window's time span, seconds.
        motion: the models' :class:`~evseg_torch.motion.MotionModel`.
        sensor_size: ``(H, W)``.
        tolerance_px: largest difference of the two models' displacements over the window, px.

    Returns:
        int64 :math:`(K,)`: the lowest cluster index of each cluster's group (its own index when it
        shares its motion with no other).
    """
    return motion_groups(moving_alike(models, boxes, duration, motion, sensor_size, tolerance_px))


def moving_alike(
    models, boxes, duration: float, motion, sensor_size, tolerance_px: float = SHARED_MOTION_PX
) -> np.ndarray:
    """Which pairs of clusters move alike, bool :math:`(K, K)` (arguments of :func:`shared_motion_groups`)."""
    models = np.asarray(models, dtype=np.float64)
    n_clusters = len(models)
    height, width = sensor_size
    boxes = np.where(np.isfinite(boxes), boxes, [0.0, 0.0, width - 1.0, height - 1.0])
    low, high = boxes[:, :2], boxes[:, :2] + boxes[:, 2:]
    close = np.eye(n_clusters, dtype=bool)
    for a in range(n_clusters):
        for b in range(a + 1, n_clusters):
            (x0, y0), (x1, y1) = np.minimum(low[a], low[b]), np.maximum(high[a], high[b])
            corners = np.array([[x0, y0], [x1, y0], [x0, y1], [x1, y1]])
            difference = motion.velocity(corners, models[a]) - motion.velocity(corners, models[b])
            close[a, b] = close[b, a] = duration * np.linalg.norm(difference, axis=-1).max() < tolerance_px
    return close


def motion_groups(close: np.ndarray) -> np.ndarray:
    """The groups of a :func:`moving_alike` matrix :math:`(K, K)`: each cluster's group named by its lowest
    cluster index, int64 :math:`(K,)`."""
    n_clusters = len(close)
    _, component = connected_components(close, directed=False)
    lowest = np.full(n_clusters, n_clusters, dtype=np.int64)
    np.minimum.at(lowest, component, np.arange(n_clusters))
    return lowest[component]

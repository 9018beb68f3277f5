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
    height, width = sensor_size
    boxes = np.where(np.isfinite(boxes), boxes, [0.0, 0.0, width - 1.0, height - 1.0])
    low, high = boxes[:, :2], boxes[:, :2] + boxes[:, 2:]
    # The corners of the box holding each pair, (K, K, 4, 2), and both models' velocities there.
    (x0, y0), (x1, y1) = (
        np.moveaxis(np.minimum(low[:, None], low[None]), -1, 0),
        np.moveaxis(np.maximum(high[:, None], high[None]), -1, 0),
    )
    corners = np.stack([np.stack(corner, axis=-1) for corner in ((x0, y0), (x1, y0), (x0, y1), (x1, y1))], 2)
    jac = motion.jacobian(corners)  # (K, K, 4, 2, P)
    first = (jac @ models[:, None, None, :, None])[..., 0]
    second = (jac @ models[None, :, None, :, None])[..., 0]
    close = duration * np.linalg.norm(first - second, axis=-1).max(axis=-1, initial=0.0) < tolerance_px
    np.fill_diagonal(close, True)
    return close


def motion_groups(close: np.ndarray) -> np.ndarray:
    """The groups of a :func:`moving_alike` matrix :math:`(K, K)`: each cluster's group named by its lowest
    cluster index, int64 :math:`(K,)`."""
    reach = np.asarray(close, dtype=bool) | np.eye(len(close), dtype=bool)
    reach |= reach.T
    # Squared until it stops growing: which clusters a chain of pairs joins (K is a window's few models).
    while not np.array_equal(grown := (reach @ reach), reach):
        reach = grown
    return reach.argmax(axis=1).astype(np.int64) if len(reach) else np.zeros(0, dtype=np.int64)

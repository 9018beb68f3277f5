"""A small generator of events from edges under known motions, for the level-two tests.

Texture points are sampled on random line segments at the reference time ``t = 0``; each becomes an
event at a time drawn uniformly in ``[0, duration]``, at the position ``x`` that the model carries the
point to, i.e. ``x - t v(x) = p`` (solved by fixed-point iterations ``x <- p + t v(x)``).
"""

from __future__ import annotations

import numpy as np
import torch

from evseg_torch.events import EventBatch
from evseg_torch.motion import Affine4, MotionModel, Rotation3D, Translation

SIZE = (96, 128)
DURATION = 0.03
# Displacements over the window of about 20 px: 2% is 0.4 px.
TRUTH = {
    "translation": (Translation(SIZE), [600.0, -400.0]),
    "affine4": (Affine4(SIZE), [600.0, -400.0, 2.0, 3.0]),
    "rotation3d": (Rotation3D(SIZE), [1.5, -2.5, 6.0]),
}


def edge_points(
    sensor_size: tuple[int, int], n_points: int, rng, n_segments: int = 12, box=(0.2, 0.2, 0.8, 0.8)
) -> np.ndarray:
    """``n_points`` points on ``n_segments`` random segments inside a box given as fractions of the
    image ``(x0, y0, x1, y1)``, :math:`(n, 2)`."""
    rng = np.random.default_rng(rng)
    height, width = sensor_size
    low = np.array([box[0] * (width - 1), box[1] * (height - 1)])
    high = np.array([box[2] * (width - 1), box[3] * (height - 1)])
    ends = rng.uniform(low, high, size=(n_segments, 2, 2))
    segment = rng.integers(0, n_segments, n_points)
    along = rng.uniform(0.0, 1.0, n_points)[:, None]
    return ends[segment, 0] + along * (ends[segment, 1] - ends[segment, 0])


def moving_events(
    model: MotionModel,
    params,
    points: np.ndarray,
    duration: float,
    rng,
    noise: float = 0.0,
    integer: bool = False,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> EventBatch:
    """Events of texture ``points`` (at ``t = 0``) moving with ``params`` over ``duration`` seconds.

    ``noise`` is the standard deviation of Gaussian jitter in pixels; ``integer`` rounds positions to
    pixels as a real sensor does. Events that leave the sensor are dropped; the rest are time-sorted.
    """
    rng = np.random.default_rng(rng)
    params = np.asarray(params, dtype=np.float64)
    t = rng.uniform(0.0, duration, len(points))
    xy = points.copy()
    for _ in range(20):
        xy = points + t[:, None] * model.velocity(xy, params)
    xy = xy + rng.normal(0.0, noise, xy.shape) if noise > 0 else xy
    xy = np.rint(xy) if integer else xy
    height, width = model.sensor_size
    inside = (xy[:, 0] >= 0) & (xy[:, 0] <= width - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= height - 1)
    order = np.argsort(t[inside], kind="stable")
    xy, t = xy[inside][order], t[inside][order]
    return EventBatch(
        xy=torch.as_tensor(xy, dtype=dtype, device=device),
        t=torch.as_tensor(t, dtype=dtype, device=device),
        p=torch.ones(len(t), dtype=dtype, device=device),
    )


def displacement_error(model: MotionModel, params, truth, events: EventBatch, duration: float) -> float:
    """Largest difference over the events' positions between the displacements over ``duration``
    predicted by ``params`` and by ``truth``, relative to the largest true displacement."""
    xy = events.xy.detach().cpu().double().numpy()
    params = np.asarray(torch.as_tensor(params).detach().cpu().double())
    truth = np.asarray(truth, dtype=np.float64)
    error = np.linalg.norm(model.velocity(xy, params) - model.velocity(xy, truth), axis=-1).max()
    return float(error / np.linalg.norm(model.velocity(xy, truth), axis=-1).max())


def edge_scene(name, seed=0, integer=True, n_points=6000, n_segments=20, dtype=torch.float64, device="cpu"):
    """Events of edges under the motion ``TRUTH[name]`` and a start 30% off each parameter:
    ``(model, truth, events, start)``."""
    model, truth = TRUTH[name]
    rng = np.random.default_rng(seed)
    points = edge_points(SIZE, n_points, rng, n_segments=n_segments)
    events = moving_events(
        model, truth, points, DURATION, rng, noise=0.2, integer=integer, dtype=dtype, device=device
    )
    start = np.asarray(truth) * (1 + 0.3 * rng.choice([-1.0, 1.0], size=len(truth)))
    return model, np.asarray(truth), events, start

"""The random parts of a scene's layout: the objects' shapes and the layers' motions."""

from __future__ import annotations

import math

import numpy as np

from evseg_torch.errors import ConfigError

_MAX_DIVERGENCE = 1.5  # affine4 divergence and rotation, 1/s
_MAX_ANGULAR = 1.0  # rotation3d angular velocity per axis, rad/s
_MAX_DRAWS = 2000  # motion candidates tried per layer before giving up


def object_shape(rng, sensor_size, area_low, area_high) -> np.ndarray:
    """A random ellipse or star polygon :math:`(V, 2)` of the drawn area, centred in the middle 60%."""
    height, width = sensor_size
    area = rng.uniform(area_low, area_high) * height * width
    if rng.random() < 0.5:
        angles = np.linspace(0, 2 * np.pi, 48, endpoint=False)
        radii = np.column_stack([np.cos(angles), rng.uniform(0.5, 1.0) * np.sin(angles)])
        turn = rng.uniform(0, np.pi)
        radii = radii @ np.array([[np.cos(turn), np.sin(turn)], [-np.sin(turn), np.cos(turn)]])
    else:
        count = int(rng.integers(5, 10))
        angles = (np.arange(count) + rng.uniform(-0.3, 0.3, count)) * (2 * np.pi / count)
        radii = rng.uniform(0.6, 1.0, count)[:, None] * np.column_stack([np.cos(angles), np.sin(angles)])
    x, y = radii.T
    radii *= math.sqrt(area / (0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))))
    centre = rng.uniform((0.2 * width, 0.2 * height), (0.8 * width, 0.8 * height))
    return centre + radii


def grid_around(points: np.ndarray) -> np.ndarray:
    """A 5x5 grid :math:`(25, 2)` over the bounding box of ``points`` :math:`(V, 2)`."""
    low, high = points.min(axis=0), points.max(axis=0)
    axes = [np.linspace(low[i], high[i], 5) for i in range(2)]
    return np.stack(np.meshgrid(*axes), axis=-1).reshape(-1, 2)


def draw_motions(models, given, regions, speeds, min_relative, slow, rng) -> list[np.ndarray]:
    """Parameters per layer: the given ones, and random ones whose mean speed over the layer's region
    is in ``speeds`` and which differ from every layer already set by at least ``min_relative`` px/s
    on average over that region."""
    params = list(given)
    for label, (model, region) in enumerate(zip(models, regions, strict=True)):
        if params[label] is not None:
            continue
        candidates = _candidates(model, rng, speeds, slow)
        velocity = model.velocity(region, candidates)  # (K, V, 2)
        mean_speed = np.linalg.norm(velocity, axis=-1).mean(axis=1)
        ok = (mean_speed >= speeds[0]) & (mean_speed <= speeds[1])
        for other_model, other in zip(models, params, strict=True):
            if other is not None:
                relative = np.linalg.norm(velocity - other_model.velocity(region, other), axis=-1)
                ok &= relative.mean(axis=1) >= min_relative
        if not ok.any():
            raise ConfigError(
                f"no {model.name} motion of mean speed in {speeds} px/s differing by at least "
                f"{min_relative} px/s from the other layers was found in {_MAX_DRAWS} draws; "
                "widen speed_range or lower min_relative_speed"
            )
        params[label] = candidates[int(np.argmax(ok))]
    return params


def _candidates(model, rng, speeds, slow) -> np.ndarray:
    """``_MAX_DRAWS`` random parameter vectors :math:`(K, P)` of the model's family."""
    speed = rng.uniform(speeds[0], speeds[1], _MAX_DRAWS)
    heading = rng.uniform(0, 2 * np.pi, _MAX_DRAWS)
    translation = speed[:, None] * np.column_stack([np.cos(heading), np.sin(heading)])
    if model.name == "translation":
        return translation
    if model.name == "affine4":
        return np.column_stack([translation, rng.uniform(-1, 1, (_MAX_DRAWS, 2)) * _MAX_DIVERGENCE * slow])
    return rng.uniform(-1, 1, (_MAX_DRAWS, model.n_params)) * _MAX_ANGULAR * slow

"""The checks of :func:`~evseg_torch.synthetic.scenes.make_scene`'s arguments, each raising a
:class:`~evseg_torch.errors.ConfigError` that names the argument."""

from __future__ import annotations

import math

import numpy as np

from evseg_torch.errors import ConfigError
from evseg_torch.motion import MOTION_MODELS, MotionModel, make_motion_model


def check_scene_size(sensor_size) -> tuple[int, int]:
    try:
        height, width = (int(v) for v in sensor_size)
        exact = all(float(v) == int(v) for v in sensor_size)
    except (TypeError, ValueError):
        raise ConfigError(f"sensor_size must be (H, W), got {sensor_size!r}") from None
    if not exact or not (16 <= height <= 32768 and 16 <= width <= 32768):
        raise ConfigError(f"sensor_size (H, W) must be integers from 16 to 32768, got {sensor_size!r}")
    return height, width


def scene_motion_models(motion_model, object_motion_models, n_objects, sensor_size) -> list[MotionModel]:
    objects = [motion_model] * n_objects if object_motion_models is None else list(object_motion_models)
    names = [motion_model, *objects]
    if len(names) != n_objects + 1:
        raise ConfigError(f"object_motion_models must name {n_objects} models, got {len(names) - 1}")
    for name in names:
        if name not in MOTION_MODELS:
            raise ConfigError(f"unknown motion model {name!r}; choose one of {sorted(MOTION_MODELS)}")
    return [make_motion_model(name, sensor_size) for name in names]


def check_layer_params(layer_params, models) -> list[np.ndarray | None]:
    if layer_params is None:
        return [None] * len(models)
    if len(layer_params) != len(models):
        raise ConfigError(
            f"layer_params must hold {len(models)} entries (background first), got {len(layer_params)}"
        )
    checked = []
    for label, (theta, model) in enumerate(zip(layer_params, models, strict=True)):
        if theta is not None:
            theta = np.array(theta, dtype=np.float64)
            if theta.shape != (model.n_params,) or not np.all(np.isfinite(theta)):
                raise ConfigError(
                    f"layer_params[{label}] must be {model.n_params} finite {model.name} parameters, "
                    f"got {theta!r}"
                )
        checked.append(theta)
    return checked


def check_positive(value, name: str) -> float:
    value = check_number(value, name)
    if not value > 0:
        raise ConfigError(f"{name} must be positive, got {value}")
    return value


def check_non_negative(value, name: str) -> float:
    value = check_number(value, name)
    if not value >= 0:
        raise ConfigError(f"{name} must be non-negative, got {value}")
    return value


def check_number(value, name: str) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(value):
        raise ConfigError(f"{name} must be finite, got {value}")
    return value


def check_polygons(shapes, n_objects: int) -> list[np.ndarray]:
    if len(shapes) != n_objects:
        raise ConfigError(f"object_shapes must hold {n_objects} polygons, got {len(shapes)}")
    polygons = [np.array(shape, dtype=np.float64) for shape in shapes]
    for k, polygon in enumerate(polygons):
        if (
            polygon.ndim != 2
            or polygon.shape[0] < 3
            or polygon.shape[1] != 2
            or not np.isfinite(polygon).all()
        ):
            raise ConfigError(
                f"object_shapes[{k}] must be finite (V, 2) vertices with V >= 3, got {polygon.shape}"
            )
    return polygons


def check_object_size(value) -> tuple[float, float]:
    low, high = check_pair(value, "object_size")
    if not 0 < low <= high < 1:
        raise ConfigError(f"object_size must be fractions 0 < low <= high < 1 of the image, got {value!r}")
    return low, high


def check_speed_range(value) -> tuple[float, float]:
    low, high = check_pair(value, "speed_range")
    if not 0 <= low <= high:
        raise ConfigError(f"speed_range must be 0 <= low <= high px/s, got {value!r}")
    return low, high


def check_pair(value, name: str) -> tuple[float, float]:
    try:
        low, high = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a pair (low, high), got {value!r}") from None
    if not (math.isfinite(low) and math.isfinite(high)):
        raise ConfigError(f"{name} must be finite, got {value!r}")
    return low, high

"""Parametric image-motion models shared by both levels (see :mod:`evseg_torch.motion.base`)."""

from evseg_torch.errors import ModelError
from evseg_torch.motion.affine4 import Affine4
from evseg_torch.motion.base import FailedEstimation, MotionEstimate, MotionModel, array_namespace
from evseg_torch.motion.rotation3d import Rotation3D
from evseg_torch.motion.translation import Translation

MOTION_MODELS: dict[str, type[MotionModel]] = {cls.name: cls for cls in (Translation, Affine4, Rotation3D)}


def make_motion_model(name: str, sensor_size: tuple[int, int], **kwargs) -> MotionModel:
    """Build a motion model by name (``translation``, ``affine4`` or ``rotation3d``)."""
    try:
        cls = MOTION_MODELS[name]
    except KeyError:
        raise ModelError(f"unknown motion model {name!r}; choose one of {sorted(MOTION_MODELS)}") from None
    return cls(sensor_size, **kwargs)


__all__ = [
    "MOTION_MODELS",
    "Affine4",
    "FailedEstimation",
    "MotionEstimate",
    "MotionModel",
    "Rotation3D",
    "Translation",
    "array_namespace",
    "make_motion_model",
]

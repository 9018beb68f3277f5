"""3-DOF camera rotation: the image motion field of a camera turning with angular velocity omega."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evseg_torch.errors import ModelError
from evseg_torch.motion.base import MotionModel, array_namespace


@dataclass(frozen=True)
class Rotation3D(MotionModel):
    """Rotational motion field with pinhole intrinsics.

    Parameters ``(w_x, w_y, w_z)``: the camera's angular velocity in rad/s, in the camera frame
    (x right, y down, z forward). With normalised coordinates ``a = (x - cx)/fx``, ``b = (y - cy)/fy``,
    the field is the instantaneous one of a static scene seen by a rotating camera:
    ``da/dt = a b w_x - (1 + a^2) w_y + b w_z`` and ``db/dt = (1 + b^2) w_x - a b w_y - a w_z``,
    times ``fx`` and ``fy`` for pixels. It is linear in omega, so 2 correspondences (4 equations)
    determine it. Events are warped with this first-order field, which differs from the exact
    rotation by ``O((|omega| dt)^2)``: under 1e-3 px for the rates and windows of the paper.

    EMSGC instead moves homogeneous *pixel* coordinates by ``dt (omega x [x, y, 1])`` with the
    origin at the top-left; that is this model with ``fx = fy = 1``, ``c = (0, 0)`` and omega negated.
    :meth:`to_paper` and :meth:`from_paper` return omega unchanged: the two parametrisations share
    the angular velocity only when the intrinsics agree, which cannot be converted in general.

    Attributes:
        focal: ``(fx, fy)`` in pixels; defaults to ``max(H, W)`` for both (about a 53 degree view).
    """

    name = "rotation3d"
    param_names = ("w_x", "w_y", "w_z")
    param_units = ("rad/s", "rad/s", "rad/s")
    min_samples = 2

    focal: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        focal = self.focal if self.focal is not None else (float(max(self.sensor_size)),) * 2
        fx, fy = (float(v) for v in focal)
        if not (fx > 0 and fy > 0):
            raise ModelError(f"focal lengths must be positive, got {focal}")
        object.__setattr__(self, "focal", (fx, fy))

    @classmethod
    def from_intrinsics(cls, sensor_size: tuple[int, int], camera_matrix: np.ndarray) -> Rotation3D:
        """Build from a 3x3 camera matrix ``K``."""
        k = np.asarray(camera_matrix, dtype=np.float64)
        if k.shape != (3, 3):
            raise ModelError(f"camera_matrix must be 3x3, got {k.shape}")
        return cls(sensor_size, principal_point=(k[0, 2], k[1, 2]), focal=(k[0, 0], k[1, 1]))

    def jacobian(self, xy):
        xp = array_namespace(xy)
        (fx, fy), (cx, cy) = self.focal, self.principal_point
        a, b = (xy[..., 0] - cx) / fx, (xy[..., 1] - cy) / fy
        rows = [
            xp.stack([fx * a * b, -fx * (1 + a * a), fx * b], axis=-1),
            xp.stack([fy * (1 + b * b), -fy * a * b, -fy * a], axis=-1),
        ]
        return xp.stack(rows, axis=-2)

    def displacement_scale(self, duration: float) -> np.ndarray:
        fx, fy = self.focal
        radius = 0.5 * float(np.hypot(*self.sensor_size))
        return float(duration) * np.array([0.5 * (fx + fy), 0.5 * (fx + fy), radius])

    def to_paper(self, params: np.ndarray) -> np.ndarray:
        return np.array(params, dtype=np.float64)

    def from_paper(self, params: np.ndarray) -> np.ndarray:
        return np.array(params, dtype=np.float64)

"""2-DOF translation (optical flow): ``v(x) = (v_x, v_y)`` in px/s."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evseg_torch.motion.base import MotionModel, jacobian_zeros


@dataclass(frozen=True)
class Translation(MotionModel):
    """Constant image velocity, parameters ``(v_x, v_y)`` in px/s; the same in the paper's convention.

    Examples:
        >>> model = Translation((180, 240))
        >>> model.warp(np.array([[10.0, 20.0]]), np.array([0.01]), np.array([100.0, -50.0])).tolist()
        [[9.0, 20.5]]
    """

    name = "translation"
    param_names = ("v_x", "v_y")
    param_units = ("px/s", "px/s")
    min_samples = 1

    def jacobian(self, xy):
        jacobian = jacobian_zeros(xy[..., 0], 2)
        jacobian[..., 0, 0] = jacobian[..., 1, 1] = 1
        return jacobian

    def displacement_scale(self, duration: float) -> np.ndarray:
        return np.full(2, float(duration))

    def to_paper(self, params: np.ndarray) -> np.ndarray:
        return np.array(params, dtype=np.float64)

    def from_paper(self, params: np.ndarray) -> np.ndarray:
        return np.array(params, dtype=np.float64)

"""4-DOF similarity motion (translation, scale, in-plane rotation): the paper's Eq. 2."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evseg_torch.motion.base import MotionModel, jacobian_zeros


@dataclass(frozen=True)
class Affine4(MotionModel):
    """Similarity velocity field about the principal point ``c``.

    Parameters ``(v_x, v_y, d, r)``: ``v(x) = (v_x, v_y) + [[d, -r], [r, d]] (x - c)``, with
    ``v_x, v_y`` in px/s and the divergence ``d`` and rotation ``r`` in 1/s. Being linear, the model
    has a 2-correspondence minimal solver and a plain least-squares refit.

    The paper (Eq. 2) writes ``v(x) = m + [(1 + m_s) R(m_theta) - I] x`` with ``x`` measured from the
    top-left pixel; so ``1 + d = (1 + m_s) cos m_theta``, ``r = (1 + m_s) sin m_theta`` and
    ``m = (v_x, v_y) - [[d, -r], [r, d]] c``. :meth:`to_paper` and :meth:`from_paper` convert.

    Examples:
        >>> model = Affine4((101, 101))  # centre (50, 50)
        >>> model.velocity(np.array([[60.0, 50.0]]), np.array([0.0, 0.0, 2.0, 0.0])).tolist()
        [[20.0, 0.0]]
    """

    name = "affine4"
    param_names = ("v_x", "v_y", "d", "r")
    param_units = ("px/s", "px/s", "1/s", "1/s")
    min_samples = 2

    def jacobian(self, xy):
        cx, cy = self.principal_point
        xc, yc = xy[..., 0] - cx, xy[..., 1] - cy
        jacobian = jacobian_zeros(xc, 4)  # rows (1, 0, xc, -yc) and (0, 1, yc, xc)
        jacobian[..., 0, 0] = jacobian[..., 1, 1] = 1
        jacobian[..., 0, 2] = jacobian[..., 1, 3] = xc
        jacobian[..., 1, 2] = yc
        jacobian[..., 0, 3] = -yc
        return jacobian

    def displacement_scale(self, duration: float) -> np.ndarray:
        radius = 0.5 * float(np.hypot(*self.sensor_size))
        return float(duration) * np.array([1.0, 1.0, radius, radius])

    def to_paper(self, params: np.ndarray) -> np.ndarray:
        params = np.asarray(params, dtype=np.float64)
        v, d, r = params[..., :2], params[..., 2], params[..., 3]
        m = v - _linear_part(d, r) @ np.asarray(self.principal_point)
        m_s = np.hypot(1.0 + d, r) - 1.0
        m_theta = np.arctan2(r, 1.0 + d)
        return np.concatenate([m, m_s[..., None], m_theta[..., None]], axis=-1)

    def from_paper(self, params: np.ndarray) -> np.ndarray:
        params = np.asarray(params, dtype=np.float64)
        m, m_s, m_theta = params[..., :2], params[..., 2], params[..., 3]
        d = (1.0 + m_s) * np.cos(m_theta) - 1.0
        r = (1.0 + m_s) * np.sin(m_theta)
        v = m + _linear_part(d, r) @ np.asarray(self.principal_point)
        return np.concatenate([v, d[..., None], r[..., None]], axis=-1)


def _linear_part(d: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The 2x2 matrices ``[[d, -r], [r, d]]``, shape (..., 2, 2)."""
    return np.stack([np.stack([d, -r], axis=-1), np.stack([r, d], axis=-1)], axis=-2)

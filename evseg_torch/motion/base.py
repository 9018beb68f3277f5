"""The shared protocol of parametric image-motion models.

Every model here is a *linear velocity field*: the image velocity of a point ``x`` is
``v(x) = J(x) @ theta`` with a model-specific Jacobian ``J(x)`` of shape (2, P). Then

* an event at time ``t`` warps to the reference time ``t_ref`` as ``x' = x - (t - t_ref) v(x)``
  (level two, motion compensation);
* a feature tracked from ``x1`` for ``dt`` seconds lands at ``x2 = x1 + dt v(x1)`` (level one), so
  every minimal solver and least-squares refit is one linear solve.

The same code serves NumPy (level one) and torch (level two, differentiable): the array functions
are written with operators and the ``stack``/``moveaxis`` functions that both libraries share, and the
namespace is picked from the argument's type. torch is never imported here, so level one stays
torch-free.

Parameters are *rates per second* in pixel units, with coordinates centred on the principal point
(image centre by default); each model documents its parameters and converts to and from the paper's
convention. For optimisers, :meth:`MotionModel.displacement_scale` gives per-parameter scales that
turn parameters (by multiplication) into pixels of displacement over a window, which conditions them alike.
"""

from __future__ import annotations

import sys
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from evseg_torch.errors import ModelError

# Faster than this, a model moves a pixel across a megapixel sensor within a microsecond.
MAX_SPEED = 1e9  # px/s


def array_namespace(array):
    """``torch`` for torch tensors, else ``numpy``; never imports torch itself."""
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(array, torch.Tensor):
        return torch
    return np


def jacobian_zeros(like, n_params: int):
    """Zeros :math:`(..., 2, P)` for the Jacobian at positions whose ``x`` coordinates are ``like``
    :math:`(...)`, in its namespace, dtype and device. The models write their non-zero entries into it:
    a third of the time of stacking all entries on 40k positions."""
    shape = (*like.shape, 2, n_params)
    if array_namespace(like) is np:
        return np.zeros(shape, dtype=np.asarray(like).dtype)
    return like.new_zeros(shape)


@dataclass(frozen=True)
class FailedEstimation:
    """Falsy result of a failed :meth:`MotionModel.from_estimate` (scikit-image's protocol)."""

    message: str

    def __bool__(self) -> bool:
        return False


@dataclass(frozen=True)
class MotionEstimate:
    """Truthy result of a successful :meth:`MotionModel.from_estimate`.

    Attributes:
        model: the motion model (family and geometry) that was fitted.
        params: fitted parameters, float64 :math:`(P,)`.
    """

    model: MotionModel
    params: np.ndarray

    def residuals(self, src, dst, dt) -> np.ndarray:
        """Euclidean transfer errors of correspondences under this estimate, :math:`(N,)`."""
        return self.model.residuals(self.params, src, dst, dt)


@dataclass(frozen=True)
class MotionModel(ABC):
    """A family of image motions on a sensor of size ``(H, W)``, stateless in its parameters.

    Class attributes ``name``, ``param_names`` and ``param_units`` name the family and the order and units
    of its parameters (the columns of every parameter array; written into results' ``models.jsonl``).

    Attributes:
        sensor_size: ``(H, W)``.
        principal_point: ``(cx, cy)`` about which scale and rotation act; defaults to the image
            centre ``((W - 1) / 2, (H - 1) / 2)``.
    """

    name: ClassVar[str]
    param_names: ClassVar[tuple[str, ...]]
    param_units: ClassVar[tuple[str, ...]]
    min_samples: ClassVar[int]

    sensor_size: tuple[int, int]
    principal_point: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        height, width = (int(v) for v in self.sensor_size)
        if height <= 0 or width <= 0:
            raise ModelError(f"sensor_size (H, W) must be positive, got {self.sensor_size}")
        object.__setattr__(self, "sensor_size", (height, width))
        if self.principal_point is None:
            object.__setattr__(self, "principal_point", ((width - 1) / 2.0, (height - 1) / 2.0))

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    def plausible(self, params) -> np.ndarray:
        """Whether each instance is an image motion of this sensor at all.

        An instance is plausible when its speed at the sensor's four corners stays within
        :data:`MAX_SPEED` px/s; beyond, the arithmetic of warps and residuals overflows float64.

        Args:
            params: :math:`(M, P)` finite parameters.

        Returns:
            bool :math:`(M,)`.
        """
        height, width = self.sensor_size
        corners = np.array([[0.0, 0.0], [width - 1.0, 0.0], [0.0, height - 1.0], [width - 1.0, height - 1.0]])
        with np.errstate(over="ignore", invalid="ignore"):
            speeds = np.linalg.norm(self.velocity(corners, np.asarray(params, dtype=np.float64)), axis=-1)
        return np.all(speeds <= MAX_SPEED, axis=-1)

    def check_instances(self, params, name: str = "initial_models") -> np.ndarray:
        """Validate a stack of model instances, e.g. a previous window's models.

        Args:
            params: :math:`(M, P)` finite, :meth:`plausible` parameters of this family.
            name: the argument's name in the error message.

        Returns:
            A float64 copy :math:`(M, P)`.

        Raises:
            ModelError: not 2-D, the wrong width, not finite, or not plausible.
        """
        instances = np.array(params, dtype=np.float64)
        if instances.ndim != 2 or instances.shape[1] != self.n_params or not np.isfinite(instances).all():
            raise ModelError(
                f"{name} must be finite ({self.n_params} columns for {self.name}) "
                f"of shape (M, {self.n_params}), got {instances.shape}"
            )
        wild = np.flatnonzero(~self.plausible(instances))
        if len(wild):
            raise ModelError(
                f"{name} row {wild[0]} moves pixels faster than {MAX_SPEED:g} px/s: not an image motion"
            )
        return instances

    @abstractmethod
    def jacobian(self, xy):
        """Velocity Jacobian at pixel positions.

        Args:
            xy: pixel coordinates :math:`(..., 2)`, NumPy array or torch tensor.

        Returns:
            :math:`(..., 2, P)` in the namespace and dtype of ``xy``.
        """

    @abstractmethod
    def displacement_scale(self, duration: float) -> np.ndarray:
        """Pixels of displacement over ``duration`` seconds caused by a unit of each parameter, at a
        typical image radius, :math:`(P,)`. Parameters times this scale are displacements in pixels,
        alike in magnitude: the units in which optimisers are conditioned."""

    @abstractmethod
    def to_paper(self, params: np.ndarray) -> np.ndarray:
        """Convert parameters :math:`(..., P)` to the paper's / EMSGC's convention."""

    @abstractmethod
    def from_paper(self, params: np.ndarray) -> np.ndarray:
        """Convert parameters :math:`(..., P)` from the paper's / EMSGC's convention."""

    def velocity(self, xy, params):
        """Image velocity in px/s of points under one or several models.

        Args:
            xy: :math:`(N, 2)` pixel coordinates.
            params: :math:`(P,)` or :math:`(K, P)`.

        Returns:
            :math:`(N, 2)` for one model, :math:`(K, N, 2)` for K models.
        """
        xp = array_namespace(xy)
        jac = self.jacobian(xy)
        if params.ndim == 1:
            return (jac @ params[:, None])[..., 0]
        return xp.moveaxis(jac @ params.T, -1, 0)

    def warp(self, xy, dt, params):
        """Warp events to the reference time: ``x' = x - dt * v(x)``.

        Args:
            xy: event positions :math:`(N, 2)`.
            dt: ``t - t_ref`` in seconds, :math:`(N,)`.
            params: :math:`(P,)` or :math:`(K, P)`.

        Returns:
            Warped positions, :math:`(N, 2)` or :math:`(K, N, 2)`; differentiable in torch.
        """
        return xy - dt[:, None] * self.velocity(xy, params)

    def predict(self, src, dt, params):
        """Where features at ``src`` are ``dt`` seconds later: ``src + dt * v(src)``.

        ``dt`` is a scalar or :math:`(N,)`; output shapes as in :meth:`velocity`.
        """
        dt = np.asarray(dt, dtype=np.float64) if array_namespace(src) is np else dt
        dt = dt[:, None] if getattr(dt, "ndim", 0) == 1 else dt
        return src + dt * self.velocity(src, params)

    def residuals(self, params, src, dst, dt) -> np.ndarray:
        """Euclidean transfer errors ``|dst - predict(src)|`` in pixels, :math:`(N,)` or :math:`(K, N)`."""
        src, dst, dt = self._check_correspondences(src, dst, dt)
        params = np.asarray(params, dtype=np.float64)
        return np.linalg.norm(dst - self.predict(src, dt, params), axis=-1)

    def from_estimate(self, src, dst, dt, weights=None) -> MotionEstimate | FailedEstimation:
        """Least-squares fit to correspondences (the minimal solver when N equals ``min_samples``).

        Args:
            src: feature positions at the earlier time, :math:`(N, 2)`.
            dst: the same features ``dt`` seconds later, :math:`(N, 2)`.
            dt: time gap in seconds, scalar or :math:`(N,)`; must be non-zero.
            weights: optional non-negative weights :math:`(N,)`.

        Returns:
            :class:`MotionEstimate`, or a falsy :class:`FailedEstimation` when the correspondences
            are too few or degenerate.
        """
        src, dst, dt = self._check_correspondences(src, dst, dt)
        if src.shape[0] < self.min_samples:
            return FailedEstimation(
                f"{self.name} needs {self.min_samples} correspondences, got {src.shape[0]}"
            )
        if weights is not None:
            weights = np.asarray(weights, dtype=np.float64)
            if weights.shape != (src.shape[0],) or np.any(weights < 0) or not np.all(np.isfinite(weights)):
                raise ModelError(f"weights must be finite, non-negative and of shape ({src.shape[0]},)")
        params, valid = self.estimate_batch(
            src[None], dst[None], dt[None], None if weights is None else weights[None]
        )
        if not valid[0]:
            return FailedEstimation(f"degenerate correspondences for {self.name}")
        return MotionEstimate(self, params[0])

    def estimate_batch(self, src, dst, dt, weights=None) -> tuple[np.ndarray, np.ndarray]:
        """Solve many small least-squares problems at once (RANSAC's minimal samples).

        Args:
            src, dst: :math:`(S, M, 2)`; dt: :math:`(S, M)`; weights: optional :math:`(S, M)`.

        Returns:
            ``(params (S, P), valid (S,))``; ``valid`` is False where the system is degenerate.
        """
        jac = self.jacobian(src) * dt[..., None, None]  # (S, M, 2, P)
        samples, count = src.shape[:2]
        a = jac.reshape(samples, 2 * count, self.n_params)
        b = (dst - src).reshape(samples, 2 * count)
        if weights is not None:
            root = np.sqrt(np.repeat(weights, 2, axis=1))
            a, b = a * root[..., None], b * root
        normal = np.swapaxes(a, 1, 2) @ a
        rhs = (np.swapaxes(a, 1, 2) @ b[..., None])[..., 0]
        # Scale-free degeneracy test: after scaling to a unit diagonal the determinant lies in [0, 1] and
        # vanishes with the smallest eigenvalue (cheaper than eigenvalues, which RANSAC would pay per sample).
        diag = np.sqrt(np.clip(np.einsum("sii->si", normal), 1e-300, None))
        scaled = normal / (diag[:, :, None] * diag[:, None, :])
        finite = np.all(np.isfinite(scaled), axis=(1, 2))
        valid = finite & (np.linalg.det(np.where(finite[:, None, None], scaled, 0.0)) > 1e-10)
        normal = np.where(valid[:, None, None], normal, np.eye(self.n_params))
        params = np.linalg.solve(normal, rhs[..., None])[..., 0]
        return np.where(valid[:, None], params, 0.0), valid

    def _check_correspondences(self, src, dst, dt):
        src = np.asarray(src, dtype=np.float64)
        dst = np.asarray(dst, dtype=np.float64)
        if src.ndim != 2 or src.shape[1] != 2 or dst.shape != src.shape:
            raise ModelError(f"src and dst must both be (N, 2), got {src.shape} and {dst.shape}")
        dt = np.broadcast_to(np.asarray(dt, dtype=np.float64), src.shape[:1]).copy()
        if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst)) and np.all(np.isfinite(dt))):
            raise ModelError("correspondences hold NaN or inf")
        if np.any(dt == 0):
            raise ModelError("correspondence time gaps dt must be non-zero")
        return src, dst, dt

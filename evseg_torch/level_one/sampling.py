"""Validated correspondences as every hypothesis of level one sees them, and NAPSAC's minimal samples.

:class:`Correspondences` holds the correspondences once checked, the linear system that every
hypothesis test and least-squares fit reuses (``dt J(src)`` and ``dst - src``), their neighbourhood
graph, and draws NAPSAC's minimal samples from it (a centre and some of its neighbours), optionally
weighted towards the points that no instance explains yet.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evseg_torch.config import LevelOneConfig
from evseg_torch.errors import ModelError, ShapeError
from evseg_torch.graphcut.problem import PottsGraph, potts_graph
from evseg_torch.level_one.neighborhood import adjacency, neighborhood_graph
from evseg_torch.motion.base import MotionModel

__all__ = ["Correspondences"]


@dataclass(frozen=True)
class Correspondences:
    """Validated correspondences with what every hypothesis test reuses.

    Attributes:
        model: the motion model.
        src, dst: :math:`(N, 2)` float64; dt: :math:`(N,)` float64.
        design: ``dt J(src)`` stacked to :math:`(2N, P)`; target: ``dst - src`` flattened, :math:`(2N,)`.
        edges: neighbourhood graph :math:`(E, 2)`.
        neighbors: :math:`(N, D)` neighbour indices padded with ``-1``, ``D`` the largest degree.
        degree: :math:`(N,)` number of neighbours.
        potts: ``edges`` as the Potts graph of PEARL's α-expansions, validated and laid out once.
    """

    model: MotionModel
    src: np.ndarray
    dst: np.ndarray
    dt: np.ndarray
    design: np.ndarray
    target: np.ndarray
    edges: np.ndarray
    neighbors: np.ndarray
    degree: np.ndarray
    potts: PottsGraph

    @classmethod
    def build(
        cls,
        src,
        dst,
        dt,
        model: MotionModel,
        *,
        neighborhood_ball_radius: float = LevelOneConfig.neighborhood_ball_radius,
        neighbors=None,
    ) -> Correspondences:
        """Validate correspondences and build the neighbourhood graph (``neighbors`` overrides it).

        Raises:
            ModelError: ``src``/``dst`` not both :math:`(N, 2)`, ``dt`` not broadcastable to
                :math:`(N,)`, NaN/inf or zero time gaps.
            ShapeError: ``neighbors`` not an :math:`(E, 2)` array of indices in ``[0, N)``.
        """
        if not isinstance(model, MotionModel):
            raise ModelError(f"model must be a MotionModel, got {type(model).__name__}")
        src = np.asarray(src, dtype=np.float64)
        dst = np.asarray(dst, dtype=np.float64)
        if src.ndim != 2 or src.shape[1] != 2 or dst.shape != src.shape:
            raise ModelError(f"src and dst must both be (N, 2), got {src.shape} and {dst.shape}")
        n_points = src.shape[0]
        dt = np.asarray(dt, dtype=np.float64)
        if dt.ndim > 1 or dt.size not in (1, n_points):
            raise ModelError(f"dt must be a scalar or ({n_points},), got shape {dt.shape}")
        dt = np.broadcast_to(dt.reshape(-1), (n_points,))
        if not (np.isfinite(src).all() and np.isfinite(dst).all() and np.isfinite(dt).all()):
            raise ModelError("correspondences hold NaN or inf")
        if np.any(dt == 0):
            raise ModelError("correspondence time gaps dt must be non-zero")
        if neighbors is None:
            edges = neighborhood_graph(dst, neighborhood_ball_radius)
        else:
            edges = np.asarray(neighbors)
            if edges.ndim != 2 or edges.shape[1] != 2 or not np.issubdtype(edges.dtype, np.integer):
                raise ShapeError(f"neighbors must be an integer (E, 2) array, got {edges.dtype}{edges.shape}")
            if edges.size and (edges.min() < 0 or edges.max() >= n_points):
                raise ShapeError(f"neighbors must index points in [0, {n_points})")
            edges = edges[edges[:, 0] != edges[:, 1]].astype(np.int64)
        indptr, indices = adjacency(edges, n_points)
        degree = np.diff(indptr)
        width = int(degree.max(initial=0))
        slot = np.arange(len(indices)) - np.repeat(indptr[:-1], degree)
        padded = np.full((n_points, width), -1, dtype=np.int64)
        padded[np.repeat(np.arange(n_points), degree), slot] = indices
        design = (model.jacobian(src) * dt[:, None, None]).reshape(2 * n_points, model.n_params)
        potts = potts_graph(edges, n_nodes=n_points)
        return cls(model, src, dst, dt, design, (dst - src).reshape(-1), edges, padded, degree, potts)

    @property
    def n_points(self) -> int:
        return self.src.shape[0]

    def sq_residuals(self, params: np.ndarray) -> np.ndarray:
        """Squared transfer errors of K hypotheses :math:`(K, P)`, shape :math:`(K, N)`."""
        diff = self.target - params @ self.design.T
        return np.square(diff[:, 0::2]) + np.square(diff[:, 1::2])

    def fit(self, index: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Least-squares fits on point subsets ``index`` :math:`(S, M)`; see ``estimate_batch``."""
        return self.model.estimate_batch(self.src[index], self.dst[index], self.dt[index], weights)

    def fit_weighted(self, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Weighted least-squares fits on all points, one per row of ``weights`` :math:`(K, N)`."""
        index = np.broadcast_to(np.arange(self.n_points), weights.shape)
        return self.fit(index, weights)

    def napsac(self, rng: np.random.Generator, count: int, weights: np.ndarray | None = None) -> np.ndarray:
        """``count`` minimal samples :math:`(count, m)`: a centre plus ``m - 1`` of its neighbours.

        Centres without enough neighbours are never drawn (NAPSAC's retry); when no point has enough,
        the samples are drawn uniformly from all points. ``weights`` :math:`(N,)`, positive, make
        centres and neighbours that many times likelier (weighted sampling without replacement);
        ``None`` draws them uniformly.
        """
        m = self.model.min_samples
        eligible = np.flatnonzero(self.degree >= m - 1)
        if eligible.size == 0:
            return np.argsort(rng.random((count, self.n_points)), axis=1)[:, :m]
        if weights is None:
            centres = eligible[rng.integers(eligible.size, size=count)]
        else:
            odds = np.cumsum(weights[eligible])
            centres = eligible[
                np.minimum(
                    np.searchsorted(odds, rng.random(count) * odds[-1], side="right"), eligible.size - 1
                )
            ]
        if m == 1:
            return centres[:, None]
        candidates = self.neighbors[centres]
        # Efraimidis-Spirakis: the m - 1 smallest exponential keys -log(u) / w are a weighted draw.
        keys = -np.log1p(-rng.random(candidates.shape))
        if weights is not None:
            keys /= weights[candidates]
        keys[candidates < 0] = np.inf
        picks = np.argpartition(keys, m - 2, axis=1)[:, : m - 1]
        return np.concatenate([centres[:, None], np.take_along_axis(candidates, picks, axis=1)], axis=1)

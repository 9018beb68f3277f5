"""Neighbourhood graph on feature correspondences (shared by NAPSAC, GC labelling and PEARL).

The graph links two correspondences when their *end* points ``dst`` (the features' positions at
the later time, i.e. on one event image) are closer than a radius. The paper builds it this way
("feature locations on one IWE ... leading to a 2D graph", Sec. IV-A), while GC-RANSAC's own code
searches the 4-D ``(src, dst)`` rows. Over a 15-35 ms window LK displacements are a few pixels, so
the 4-D distance differs from the 2-D one by at most that much; the 2-D graph is simpler and
matches the paper.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from evseg_torch.errors import ConfigError, ShapeError


def neighborhood_graph(points, radius: float) -> np.ndarray:
    """Undirected radius graph of 2-D points.

    Args:
        points: positions :math:`(N, 2)`, normally the correspondences' ``dst``.
        radius: link points closer than this (Euclidean, inclusive), in pixels.

    Returns:
        Edges :math:`(E, 2)` int64, each pair once with ``i < j``, sorted lexicographically.

    Examples:
        >>> neighborhood_graph(np.array([[0.0, 0.0], [3.0, 4.0], [20.0, 0.0]]), 5.0).tolist()
        [[0, 1]]
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        raise ShapeError(f"points must be (N, 2), got {points.shape}")
    if not radius > 0:
        raise ConfigError(f"neighborhood radius must be positive, got {radius}")
    pairs = cKDTree(points).query_pairs(float(radius), output_type="ndarray").astype(np.int64)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))].reshape(-1, 2)


def adjacency(edges: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Compressed neighbour lists of an undirected edge array.

    Args:
        edges: :math:`(E, 2)` node indices in ``[0, n_points)``.
        n_points: number of nodes N.

    Returns:
        ``(indptr (N + 1,), indices (2E,))``: the neighbours of node ``i`` are
        ``indices[indptr[i]:indptr[i + 1]]``.
    """
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    heads = np.concatenate([edges[:, 0], edges[:, 1]])
    tails = np.concatenate([edges[:, 1], edges[:, 0]])
    order = np.argsort(heads, kind="stable")
    indptr = np.zeros(n_points + 1, dtype=np.int64)
    np.cumsum(np.bincount(heads, minlength=n_points), out=indptr[1:])
    return indptr, tails[order]

"""The truncated-quadratic preference of points for a model, and GC-RANSAC's graph-cut inlier labelling.

:func:`preference` is each point's MSAC score for a model (Progressive-X's preference vector entry);
:func:`graph_cut_inliers` labels the inliers of one model with one s-t minimum cut, so that
neighbouring points tend to share their label (Barath and Matas, CVPR 2018). Both GC-RANSAC
(:mod:`~evseg_torch.level_one.gc_ransac`) and PEARL (:mod:`~evseg_torch.level_one.progressive_x`) use
them.
"""

from __future__ import annotations

import maxflow
import numpy as np

__all__ = ["graph_cut_inliers", "preference"]


def preference(sq_residuals, threshold: float) -> np.ndarray:
    """Truncated-quadratic preference ``max(0, 1 - r^2 / (1.5 threshold)^2)`` of points for models.

    It is each point's MSAC score for a model, Progressive-X's preference vector entry, and positive
    exactly for the inliers at the truncated threshold ``1.5 * threshold``.

    Args:
        sq_residuals: squared transfer errors in px^2, any shape.
        threshold: inlier threshold ``tau`` in pixels.

    Returns:
        Preferences in ``[0, 1]``, same shape.
    """
    return np.clip(1.0 - np.asarray(sq_residuals) / (1.5 * threshold) ** 2, 0.0, None)


def graph_cut_inliers(
    sq_residuals, edges, *, threshold: float, spatial_coherence_weight: float
) -> np.ndarray:
    """Spatially coherent inlier/outlier labelling of one model by an s-t minimum cut (GC-RANSAC).

    With ``d_i = r_i^2 / (1.5 tau)^2`` and ``w`` the spatial coherence weight, a point inside the
    truncated threshold (``d_i < 1``) pays ``(1 - w)(1 - d_i)`` for being labelled an outlier, one
    outside pays ``(1 - w) d_i`` for being labelled an inlier; every neighbour pair pays ``w`` if
    labelled differently and ``w (min(d_i, 1) + min(d_j, 1)) / 2`` if both are outliers (GC-RANSAC's
    energy). The pair term is submodular, so one minimum cut gives the exact optimum. With ``w = 0``
    this is plain thresholding at ``1.5 tau``.

    Args:
        sq_residuals: squared residuals of the points under the model, :math:`(N,)`.
        edges: neighbourhood graph :math:`(E, 2)`, each pair once.
        threshold: inlier threshold ``tau`` in pixels.
        spatial_coherence_weight: ``w`` in ``[0, 1]``.

    Returns:
        Boolean inlier mask :math:`(N,)`.
    """
    ratio = np.asarray(sq_residuals, dtype=np.float64) / (1.5 * threshold) ** 2
    distance = np.minimum(ratio, 1.0)
    n_points = ratio.shape[0]
    weight = float(spatial_coherence_weight)
    # Linear cost of labelling a point inlier rather than outlier; the pair terms are rewritten as
    # E(x_i, x_j) = E00 + (E10 - E00) x_i + (E11 - E10) x_j + (E01 + E10 - E00 - E11)(1 - x_i) x_j.
    linear = (1.0 - weight) * np.where(ratio < 1.0, ratio - 1.0, ratio)
    tail, head = edges[:, 0], edges[:, 1]
    both_out = 0.5 * weight * (distance[tail] + distance[head])
    linear += np.bincount(tail, weights=weight - both_out, minlength=n_points)
    linear -= np.bincount(head, minlength=n_points) * weight
    graph = maxflow.Graph[float](n_points, len(edges))
    nodes = graph.add_nodes(n_points)
    graph.add_edges(tail, head, 2.0 * weight - both_out, np.zeros(len(edges)))
    # Sink side = inlier: the source edge is cut (paid) by inliers, the sink edge by outliers.
    graph.add_grid_tedges(nodes, np.clip(linear, 0.0, None), np.clip(-linear, 0.0, None))
    graph.maxflow()
    return graph.get_grid_segments(nodes)

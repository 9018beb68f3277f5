"""One α-expansion move's graph as one compiled pass over the nodes and one over the edges (Numba).

:func:`~evseg_torch.graphcut.alpha_expansion._expand` builds each move's cut from about twenty NumPy
passes over the labels and edges (gathers, masks, weighted bincounts); on level two's graphs of 3–15k
nodes their calls take a third of the move beside the maximum flow. :func:`move_terms` computes the same
arrays in two loops, each sum accumulated in NumPy's order (``bincount`` adds its weights in input order
from zero), so the graph handed to PyMaxflow, and the cut, are the same bit for bit (tested). Numba is the
optional ``fast`` extra; without it the NumPy code runs.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def move_terms(labels, alpha, unary, tail, head, weight, graph_tail, graph_head, node_id):
    """The arrays of one α-move (see :func:`~evseg_torch.graphcut.alpha_expansion._expand`).

    Args:
        labels: int64 current labels :math:`(N,)`.
        alpha: the expanding label.
        unary: float64 data costs :math:`(N, L)`.
        tail, head, weight, graph_tail, graph_head: the layout's edges (caller's and graph ids) and weights.
        node_id: each node's graph id :math:`(N,)`.

    Returns:
        ``(slack, counts, pairs, moving)``: per label, its nodes' data-cost rise under α minus the weight
        of its boundary, and its node count :math:`(L,)`; the edges between movable nodes as graph ids
        and capacities ``(tail, head, forward, backward)``; the movable nodes, their graph ids and their
        capacities towards α and towards keeping ``(movable, ids, to_alpha, to_keep)``.
    """
    n_nodes, n_labels = unary.shape
    keep_data = np.empty(n_nodes)
    rise = np.zeros(n_labels)
    counts = np.zeros(n_labels, np.int64)
    n_movable = 0
    for i in range(n_nodes):
        keep_data[i] = unary[i, labels[i]]
    for i in range(n_nodes):
        rise[labels[i]] += unary[i, alpha] - keep_data[i]
        counts[labels[i]] += 1
        n_movable += labels[i] != alpha
    # Potts edges: the boundary weights each node keeps paying (to its head, or its tail where the head
    # is α), each label's boundary seen from its tails and from its heads, and the pairs of movable ends.
    kept = np.zeros(n_nodes)
    from_tails = np.zeros(n_labels)
    from_heads = np.zeros(n_labels)
    pair_tail = np.empty(len(tail), np.uint32)
    pair_head = np.empty(len(tail), np.uint32)
    forward = np.empty(len(tail))
    backward = np.empty(len(tail))
    n_pairs = 0
    for e in range(len(tail)):
        tail_label, head_label = labels[tail[e]], labels[head[e]]
        differ = tail_label != head_label
        boundary = weight[e] * differ
        kept[head[e] if head_label != alpha else tail[e]] += boundary
        from_tails[tail_label] += boundary
        from_heads[head_label] += boundary
        if tail_label != alpha and head_label != alpha:
            pair_tail[n_pairs], pair_head[n_pairs] = graph_tail[e], graph_head[e]
            forward[n_pairs] = weight[e]
            backward[n_pairs] = 0.0 if differ else weight[e]
            n_pairs += 1
    movable = np.empty(n_movable, np.int64)
    ids = np.empty(n_movable, np.int64)
    to_alpha = np.empty(n_movable)
    to_keep = np.empty(n_movable)
    m = 0
    for i in range(n_nodes):
        if labels[i] != alpha:
            movable[m], ids[m] = i, node_id[i]
            to_alpha[m], to_keep[m] = unary[i, alpha], keep_data[i] + kept[i]
            m += 1
    pairs = (pair_tail[:n_pairs], pair_head[:n_pairs], forward[:n_pairs], backward[:n_pairs])
    return rise - (from_tails + from_heads), counts, pairs, (movable, ids, to_alpha, to_keep)

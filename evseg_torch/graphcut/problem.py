"""The labelling problem of the graph cuts: its arguments checked, its graph's layout, and its energy.

:func:`prepare_problem` validates an energy (unary costs, a Potts edge set, its smoothness weight, label
costs, group costs paid once per group of labels in use, an optional outlier label) into a float64
:class:`LabellingProblem`; :func:`potts_graph` validates an edge set once and numbers its graph's nodes
for the maximum flow (:class:`GraphLayout`), so a graph labelled several times pays that once;
:func:`labeling_energy` is the energy of a labelling, against which
:func:`~evseg_torch.graphcut.alpha_expansion.alpha_expansion` accepts each move.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import reverse_cuthill_mckee

from evseg_torch.errors import EvsegError, ShapeError
from evseg_torch.validation import check_integer

__all__ = [
    "GraphCutError",
    "GraphLayout",
    "LabellingProblem",
    "PottsGraph",
    "graph_layout",
    "internal_labels",
    "labeling_energy",
    "potts_graph",
    "prepare_problem",
    "problem_energy",
]


class GraphCutError(EvsegError, ValueError):
    """A graph-cut argument holds an invalid value (negative weight, NaN, label out of range)."""


@dataclass(frozen=True)
class GraphLayout:
    """Node numbering and edge order of the cut graphs, chosen once per edge set for memory locality.

    Maximum flow on a neighbourhood graph whose node ids are scattered (events sorted by time, random
    points) is much slower than on a bandwidth-reducing (reverse Cuthill-McKee) numbering with the
    edges sorted by their first end, so the graphs use that numbering; energies keep the caller's
    order.
    """

    node_id: np.ndarray  # (N,) graph node id of every node
    graph_order: np.ndarray  # (N,) node of every graph id, the inverse permutation of node_id
    tail: np.ndarray  # (E',) caller's node indices, edges in graph order, graph_tail < graph_head
    head: np.ndarray
    graph_tail: np.ndarray  # (E',) uint32 graph node ids, as PyMaxflow stores them
    graph_head: np.ndarray
    weight: np.ndarray  # (E',) positive


@dataclass(frozen=True)
class PottsGraph:
    """A validated Potts edge set with the node numbering of its cut graphs, reusable across calls.

    Build it with :func:`potts_graph` and pass it as ``edges`` to :func:`alpha_expansion` or
    :func:`labeling_energy` when the same graph is labelled several times (level two's outer rounds):
    the validation and the reverse Cuthill-McKee numbering are then paid once.

    Attributes:
        n_nodes: number of nodes the edges index.
        n_edges: number of edges kept (positive weight, distinct ends).
    """

    n_nodes: int
    layout: GraphLayout

    @property
    def n_edges(self) -> int:
        return len(self.layout.weight)


@dataclass(frozen=True)
class LabellingProblem:
    """Validated float64 copy of an energy; the outlier label, if any, is the last column."""

    unary: np.ndarray  # (N, Lp)
    layout: GraphLayout  # weights already multiplied by the smoothness
    label_cost: np.ndarray  # (Lp,)
    has_outlier: bool
    label_group: np.ndarray  # (Lp,) each label's group, -1 for none (the outlier label's is -1)
    group_cost: np.ndarray  # (G,) paid once for every group with a label in use

    @property
    def n_labels(self) -> int:
        return self.unary.shape[1]


def _finite_scalar(value, name: str, *, nonnegative: bool) -> float:
    array = np.asarray(value)
    if array.ndim != 0:
        raise ShapeError(f"{name} must be a scalar, got shape {array.shape}")
    if not np.issubdtype(array.dtype, np.number) or np.iscomplexobj(array):
        raise GraphCutError(f"{name} must be a real number, got {value!r}")
    scalar = float(array)
    if not np.isfinite(scalar):
        raise GraphCutError(f"{name} must be finite, got {scalar}")
    if nonnegative and scalar < 0:
        raise GraphCutError(f"{name} must be non-negative, got {scalar}")
    return scalar


def _real_array(value, name: str) -> np.ndarray:
    array = np.asarray(value)
    if not (np.issubdtype(array.dtype, np.number) or array.dtype == np.bool_) or np.iscomplexobj(array):
        raise GraphCutError(f"{name} must hold real numbers, got dtype {array.dtype}")
    array = array.astype(np.float64)
    if not np.isfinite(array).all():
        raise GraphCutError(f"{name} must be finite (found NaN or inf)")
    return array


def _integer_array(value, name: str) -> np.ndarray:
    array = np.asarray(value)
    if array.size and not np.issubdtype(array.dtype, np.integer):
        raise GraphCutError(f"{name} must be an integer array, got dtype {array.dtype}")
    return array.astype(np.intp)


def _edge_arrays(edges, edge_weights, n_nodes: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validated ``(tail, head, weight)``; self-loops and zero weights never cost anything and are dropped."""
    pairs = _integer_array(edges, "edges")
    if pairs.ndim != 2 or pairs.shape[1] != 2:
        raise ShapeError(f"edges must have shape (E, 2), got {pairs.shape}")
    if pairs.size and (pairs.min() < 0 or pairs.max() >= n_nodes):
        raise GraphCutError(
            f"edges must index nodes in [0, {n_nodes}), got values in [{pairs.min()}, {pairs.max()}]"
        )
    if edge_weights is None:
        weight = np.ones(len(pairs))
    else:
        weight = _real_array(edge_weights, "edge_weights")
        if weight.shape != (len(pairs),):
            raise ShapeError(f"edge_weights must have shape ({len(pairs)},) like edges, got {weight.shape}")
        if (weight < 0).any():
            raise GraphCutError("edge_weights must be non-negative")
    keep = (weight > 0) & (pairs[:, 0] != pairs[:, 1])
    return pairs[keep, 0], pairs[keep, 1], weight[keep]


def prepare_problem(
    unary,
    edges,
    edge_weights,
    smoothness,
    label_cost,
    outlier_cost,
    outlier_label_cost,
    reorder=True,
    label_groups=None,
    group_cost=None,
) -> LabellingProblem:
    data = _real_array(unary, "unary")
    if data.ndim != 2 or data.shape[1] == 0:
        raise ShapeError(f"unary must have shape (N, L) with L >= 1, got {data.shape}")
    n_nodes, n_labels = data.shape

    if isinstance(edges, PottsGraph):
        if edge_weights is not None:
            raise GraphCutError("edge_weights must be None with a PottsGraph, whose weights are built in")
        if edges.n_nodes != n_nodes:
            raise ShapeError(f"the PottsGraph has {edges.n_nodes} nodes but unary has {n_nodes} rows")
        layout = edges.layout
    else:
        layout = graph_layout(n_nodes, *_edge_arrays(edges, edge_weights, n_nodes), reorder=reorder)
    scale = _finite_scalar(smoothness, "smoothness", nonnegative=True)
    if scale == 0:
        layout = graph_layout(n_nodes, *(np.zeros(0, dtype=np.intp),) * 2, np.zeros(0), reorder=False)
    elif scale != 1:
        layout = replace(layout, weight=layout.weight * scale)

    costs = _real_array(label_cost, "label_cost")
    if costs.ndim == 0:
        costs = np.full(n_labels, float(costs))
    elif costs.shape != (n_labels,):
        raise ShapeError(f"label_cost must be a scalar or have shape ({n_labels},), got {costs.shape}")
    if (costs < 0).any():
        raise GraphCutError("label_cost must be non-negative")

    label_group, group_costs = _group_arrays(label_groups, group_cost, n_labels)
    has_outlier = outlier_cost is not None
    if has_outlier:
        outlier = _finite_scalar(outlier_cost, "outlier_cost", nonnegative=False)
        data = np.concatenate([data, np.full((n_nodes, 1), outlier)], axis=1)
        costs = np.append(costs, _finite_scalar(outlier_label_cost, "outlier_label_cost", nonnegative=True))
        label_group = np.append(label_group, -1)
    return LabellingProblem(data, layout, costs, has_outlier, label_group, group_costs)


def _group_arrays(label_groups, group_cost, n_labels: int) -> tuple[np.ndarray, np.ndarray]:
    """Validated ``(label_group, group_cost)``: every label in no group when both are ``None``."""
    if (label_groups is None) != (group_cost is None):
        raise GraphCutError("label_groups and group_cost go together: give both or neither")
    if label_groups is None:
        return np.full(n_labels, -1, dtype=np.intp), np.zeros(0)
    groups = _integer_array(label_groups, "label_groups")
    costs = _real_array(group_cost, "group_cost")
    if groups.shape != (n_labels,):
        raise ShapeError(f"label_groups must have shape ({n_labels},), got {groups.shape}")
    if costs.ndim != 1:
        raise ShapeError(f"group_cost must have shape (G,), got {costs.shape}")
    if groups.size and (groups.min() < -1 or groups.max() >= len(costs)):
        raise GraphCutError(
            f"label_groups must lie in [-1, {len(costs)}) for {len(costs)} group costs, got values in "
            f"[{groups.min()}, {groups.max()}]"
        )
    if (costs < 0).any():
        raise GraphCutError("group_cost must be non-negative")
    return groups, costs


def internal_labels(labels, problem: LabellingProblem, name: str) -> np.ndarray:
    """Map public labels (``-1`` = outlier) to column indices of ``problem.unary``."""
    array = _integer_array(labels, name)
    n_nodes = problem.unary.shape[0]
    if array.shape != (n_nodes,):
        raise ShapeError(f"{name} must have shape ({n_nodes},), got {array.shape}")
    n_models = problem.n_labels - problem.has_outlier
    low = -1 if problem.has_outlier else 0
    if array.size and (array.min() < low or array.max() >= n_models):
        raise GraphCutError(
            f"{name} must lie in [{low}, {n_models}) (-1 only with outlier_cost), got "
            f"values in [{array.min()}, {array.max()}]"
        )
    return np.where(array < 0, problem.n_labels - 1, array)


def problem_energy(problem: LabellingProblem, labels: np.ndarray) -> float:
    unary = np.take_along_axis(problem.unary, labels[:, None], axis=1).sum()
    layout = problem.layout
    potts = layout.weight[labels[layout.tail] != labels[layout.head]].sum()
    used = np.bincount(labels, minlength=problem.n_labels) > 0
    groups_used = np.zeros(len(problem.group_cost), dtype=bool)
    groups_used[problem.label_group[used & (problem.label_group >= 0)]] = True
    return (
        float(unary)
        + float(potts)
        + float(problem.label_cost[used].sum())
        + float(problem.group_cost[groups_used].sum())
    )


def labeling_energy(
    labels,
    unary,
    edges,
    edge_weights=None,
    *,
    smoothness=1.0,
    label_cost=0.0,
    outlier_cost=None,
    outlier_label_cost=0.0,
    label_groups=None,
    group_cost=None,
) -> float:
    """Energy of a labelling: data + Potts + label costs + group costs (see the module docstring).

    Args:
        labels: integer :math:`(N,)` labels in ``[0, L)``, or ``-1`` (outlier) if ``outlier_cost`` is set.
        unary: data costs :math:`(N, L)`.
        edges: integer node pairs :math:`(E, 2)`, each undirected edge listed once; duplicates add up;
            or a :class:`PottsGraph` (then ``edge_weights`` must be ``None``).
        edge_weights: non-negative :math:`(E,)`; ones by default.
        smoothness: non-negative Potts weight λ, multiplying every edge weight.
        label_cost: non-negative scalar or :math:`(L,)`, paid once for every label in use.
        outlier_cost: constant data cost of the outlier label at every node; ``None`` for no outlier label.
        outlier_label_cost: label cost of the outlier label.
        label_groups: each label's group, integer :math:`(L,)` in ``[-1, G)`` (-1: in none), with
            ``group_cost``; ``None`` for no groups.
        group_cost: non-negative :math:`(G,)`, paid once for every group with a label in use.

    Returns:
        The energy as a Python float.

    Raises:
        ShapeError: an argument has the wrong shape.
        GraphCutError: negative weights or costs, NaN or inf, labels or node indices out of range.
    """
    problem = prepare_problem(
        unary,
        edges,
        edge_weights,
        smoothness,
        label_cost,
        outlier_cost,
        outlier_label_cost,
        reorder=False,
        label_groups=label_groups,
        group_cost=group_cost,
    )
    return problem_energy(problem, internal_labels(labels, problem, "labels"))


def graph_layout(n_nodes: int, tail, head, weight, reorder: bool = True) -> GraphLayout:
    graph_order = np.arange(n_nodes)
    if reorder and len(tail):
        ends = np.concatenate([tail, head])
        adjacency = sparse.csr_array(
            (np.ones(len(ends), dtype=np.int32), (ends, np.roll(ends, len(tail)))), shape=(n_nodes, n_nodes)
        )
        graph_order = reverse_cuthill_mckee(adjacency, symmetric_mode=True).astype(np.intp)
    node_id = np.empty(n_nodes, dtype=np.intp)
    node_id[graph_order] = np.arange(n_nodes)
    first = node_id[tail] < node_id[head]
    tail, head = np.where(first, tail, head), np.where(first, head, tail)
    order = np.argsort(node_id[tail], kind="stable")
    tail, head = tail[order], head[order]
    return GraphLayout(
        node_id,
        graph_order,
        tail,
        head,
        node_id[tail].astype(np.uint32),
        node_id[head].astype(np.uint32),
        weight[order],
    )


def potts_graph(edges, edge_weights=None, *, n_nodes: int, reorder: bool = True) -> PottsGraph:
    """Validate a Potts edge set once and choose the node numbering of its cut graphs.

    Args:
        edges: integer node pairs :math:`(E, 2)`, each undirected edge listed once; duplicates add up.
        edge_weights: non-negative :math:`(E,)`; ones by default. The ``smoothness`` of each call
            multiplies them.
        n_nodes: number of nodes, the ``N`` of the unary costs it will be used with.
        reorder: number the cut graphs' nodes in reverse Cuthill-McKee order (see :class:`GraphLayout`);
            ``False`` keeps the caller's numbering, as good when it already follows space (pixels in
            row-major order: level two's sites) and cheaper, as no numbering is computed.

    Returns:
        :class:`PottsGraph`, to pass as ``edges`` (with ``edge_weights=None``).

    Raises:
        ShapeError: an argument has the wrong shape.
        GraphCutError: negative weights, NaN or inf, node indices out of range.

    Example:
        >>> from evseg_torch.graphcut import alpha_expansion
        >>> graph = potts_graph(np.array([[0, 1], [1, 2]]), n_nodes=3)
        >>> alpha_expansion(np.array([[0.0, 2.0], [2.0, 0.0], [0.0, 2.0]]), graph, smoothness=3.0).labels
        array([0, 0, 0])
    """
    n_nodes = check_integer(n_nodes, "n_nodes", error=GraphCutError)
    return PottsGraph(
        n_nodes, graph_layout(n_nodes, *_edge_arrays(edges, edge_weights, n_nodes), reorder=reorder)
    )

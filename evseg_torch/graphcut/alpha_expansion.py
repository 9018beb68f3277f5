"""Multi-label α-expansion with Potts smoothness, label costs and an optional outlier label.

The energy of a labelling ``f`` of ``N`` nodes with labels ``0 .. L-1`` is

.. math::

    E(f) = \\sum_i U_{i, f_i} + \\lambda \\sum_{(i, j)} w_{ij} [f_i \\ne f_j] + \\sum_{l \\text{ used}} h_l

(data + Potts + MDL label costs, EMSGC's and Progressive-X's PEARL energy), plus, where labels are
grouped, a cost :math:`h_g` paid once for every group :math:`g` with a label in use (Delong et al.'s
label *subset* costs: level two's labels of one motion share its cost). With ``outlier_cost`` set, an
extra label, reported as ``-1``, costs ``outlier_cost`` at every node and ``outlier_label_cost`` once if
used.

Each α-move is one s-t minimum cut on a :class:`maxflow.Graph` (PyMaxflow) built with array calls only.
Node ``i`` on the sink side takes α, on the source side keeps ``f_i``; nodes already labelled α are not
part of the cut (their edges become unary terms of their neighbours). A Potts edge between two nodes
that may move is split, as in Kolmogorov and Zabih (2004), into unary terms and one submodular pair:

* ``f_i == f_j``: the cost is ``w [x_i != x_j]``, an edge of capacity ``w`` both ways;
* ``f_i != f_j``: the cost is ``w (1 - x_i x_j) = w (1 - x_j) + w (1 - x_i) x_j``, i.e. ``w`` on ``j``
  keeping its label plus an edge ``i -> j`` of capacity ``w``.

Label costs follow Delong et al. (IJCV 2012): the cut pays ``h_l`` for a label ``l != α`` in use exactly
when some node of ``l`` keeps it, through auxiliary nodes (a root paying ``h_l`` on the source side, fed
by every node of ``l`` through edges of capacity ``h_l``; see :func:`_add_label_costs` for the two-level
version used here); a group's cost gets the same gadget, fed by every node of the group's labels, when
α is not in the group. α's own cost ``h_α [any node takes α]`` is not submodular when α is unused; it is
handled by comparing energies, which is *exact* for the move: if the cut's best labelling moves some
node to α it is also the best labelling among those that use α, and the other candidate, moving
nothing, is the current labelling. The same holds for the cost of α's group, a constant of every
labelling that uses α. So every move is the optimal expansion move.

A label that no optimal move can drop gets no gadget (:func:`_retained_labels`): dropping ``l`` means
moving all of its nodes to α, which costs at least their data-cost rise minus the weight of ``l``'s
boundary; when that exceeds ``h_l``, ``h_l`` is a constant of the move. This leaves the cut's minima
unchanged and, in level two, removes most gadgets and a good part of the labelling time. Fixing single
nodes whose data cost for α exceeds their own by more than their smoothness weights, the usual pruning,
is not done: in level two the Potts terms dominate, and it would fix only a few of the movable sites.

A move is accepted only if :func:`labeling_energy` strictly decreases, which also guards against
floating-point noise in the cut. A label is skipped when no other label's move has changed the labelling
since its own last attempt, because the optimal α-expansion of an α-expansion result is that result
itself; the loop stops when every label would be skipped, which is how "a whole cycle changed nothing"
shows up.

Speed: the graphs number the nodes in reverse Cuthill-McKee order, computed once per edge set (see
:class:`_Layout`; a :class:`PottsGraph` from :func:`potts_graph` carries it across calls), and are
built from precomputed edge arrays with a handful of vectorised passes per move, or two compiled loops
where Numba is installed (:mod:`~evseg_torch.kernels.expansion`, the same graphs bit for bit);
the maximum flow itself (Boykov-Kolmogorov, single-threaded) takes most of the time.
"""

from __future__ import annotations

from dataclasses import dataclass

import maxflow
import numpy as np

from evseg_torch.backend import kernel
from evseg_torch.graphcut.problem import (
    GraphCutError,
    LabellingProblem,
    internal_labels,
    prepare_problem,
    problem_energy,
)
from evseg_torch.validation import check_integer

__all__ = ["ExpansionResult", "alpha_expansion"]


@dataclass(frozen=True)
class ExpansionResult:
    """Result of :func:`alpha_expansion`.

    Attributes:
        labels: int64 :math:`(N,)` labels in ``[0, L)``, or ``-1`` for the outlier label.
        energy: :func:`labeling_energy` of ``labels``.
        energy_history: energy of the initial labelling and after each cycle, non-increasing.
        n_cycles: number of expansion cycles run (cycles in which at least one move was tried).
    """

    labels: np.ndarray
    energy: float
    energy_history: tuple[float, ...]
    n_cycles: int


# Members per group node of the label-cost gadget (see _add_label_costs).
_GROUP_SIZE = 32


def _add_label_costs(graph, label_cost, member_label, members, n_groups) -> None:
    """Delong et al.'s label-cost gadget for every label with ``n_groups > 0``, on a two-level tree.

    Label ``l`` gets a root node paying ``h_l`` on the source side; its ``members`` (graph ids, sorted)
    are split into runs of ``_GROUP_SIZE`` consecutive ids, each run feeding one group node by edges of
    capacity ``h_l``, and each group node feeds the root by an edge of capacity ``h_l``. The cut pays
    ``h_l`` exactly when some member keeps ``l``, as with a single hub node, but the maximum flow does
    not have to scan one node with thousands of arcs, which is markedly faster on large graphs.
    """
    labelled = np.flatnonzero(n_groups)
    label_cost = label_cost[labelled]
    roots = graph.add_nodes(len(labelled))
    graph.add_grid_tedges(roots, np.zeros(len(labelled)), label_cost)
    group_of_label = np.repeat(np.arange(len(labelled)), n_groups[labelled])
    groups = graph.add_nodes(len(group_of_label))
    graph.add_edges(groups, roots[group_of_label], label_cost[group_of_label], np.zeros(len(groups)))

    slot = np.zeros(len(n_groups), dtype=np.intp)
    slot[labelled] = np.arange(len(labelled))
    member_slot = slot[member_label]
    by_label = np.argsort(member_slot, kind="stable")
    member_slot = member_slot[by_label]
    counts = np.bincount(member_slot, minlength=len(labelled))
    rank = np.arange(len(members)) - np.repeat(np.cumsum(counts) - counts, counts)
    first_group = np.cumsum(n_groups[labelled]) - n_groups[labelled]
    graph.add_edges(
        members[by_label],
        groups[first_group[member_slot] + rank // _GROUP_SIZE],
        label_cost[member_slot],
        np.zeros(len(members)),
    )


def _gadget(cost: np.ndarray, charged: np.ndarray, owner: np.ndarray):
    """The arguments of :func:`_add_label_costs` for the charged ones of some costs (labels' or groups').

    Args:
        cost: each owner's cost :math:`(O,)`.
        charged: which owners the cut charges, bool :math:`(O,)`.
        owner: each node's owner in graph order, -1 for none, :math:`(N,)`.

    Returns:
        ``(cost, member_owner, members, n_groups)``: the members' owners, the members (graph ids, sorted)
        and each owner's number of group nodes (0 when not charged).
    """
    if not charged.any():
        return cost, owner[:0], owner[:0], np.zeros(len(cost), dtype=np.intp)
    members = np.flatnonzero((owner >= 0) & charged[np.maximum(owner, 0)])
    member_owner = owner[members]
    n_groups = -(-np.bincount(member_owner, minlength=len(cost)) // _GROUP_SIZE)
    return cost, member_owner, members, n_groups


def _move_terms(problem: LabellingProblem, labels: np.ndarray, alpha: int):
    """The arrays of one α-move: the NumPy form of :func:`~evseg_torch.kernels.expansion.move_terms`
    (the same returns, bit for bit)."""
    layout = problem.layout
    n_nodes, n_labels = problem.unary.shape
    tail_label = labels[layout.tail]
    head_label = labels[layout.head]
    head_movable = head_label != alpha
    differ = tail_label != head_label
    pair = np.flatnonzero((tail_label != alpha) & head_movable)

    # Cost of keeping the current label (paid on the source side): the data cost, Potts edges to
    # α-nodes and the "w on head keeping" part of pairs whose ends differ. An edge whose head is α
    # charges its tail; edges between two α-nodes have equal ends and charge nothing.
    keep_data = np.take_along_axis(problem.unary, labels[:, None], axis=1)[:, 0]
    boundary_weight = layout.weight * differ
    keep_cost = keep_data + np.bincount(
        np.where(head_movable, layout.head, layout.tail), weights=boundary_weight, minlength=n_nodes
    )
    rise = np.bincount(labels, weights=problem.unary[:, alpha] - keep_data, minlength=n_labels)
    boundary = np.bincount(tail_label, weights=boundary_weight, minlength=n_labels) + np.bincount(
        head_label, weights=boundary_weight, minlength=n_labels
    )
    pair_weight = layout.weight.take(pair)
    pairs = (
        layout.graph_tail.take(pair),
        layout.graph_head.take(pair),
        pair_weight,
        np.where(differ.take(pair), 0.0, pair_weight),
    )
    movable = np.flatnonzero(labels != alpha)
    moving = (movable, layout.node_id.take(movable), problem.unary[movable, alpha], keep_cost.take(movable))
    return rise - boundary, np.bincount(labels, minlength=n_labels), pairs, moving


def _retained_labels(problem: LabellingProblem, slack: np.ndarray) -> np.ndarray:
    """The labels that every optimal α-move keeps in use; their label costs are constants of the move.

    A move drops a label ``l != α`` only by moving all of ``l``'s nodes to α. Against the same move with
    those nodes kept, that raises the data cost by the sum of ``U[:, α] - U[:, l]`` over them, lowers the
    Potts energy by at most the weight of ``l``'s boundary (edges inside ``l`` cost nothing either way,
    edges leaving it at most their weight) and saves ``h_l``, and its group's cost if ``l`` was the
    group's last label in use. When the rise exceeds the other two, no optimal move drops ``l``.

    Args:
        problem: the energy.
        slack: per label, the data-cost rise of moving all its nodes to α minus the weight of its
            boundary, :math:`(L,)` (from the move's terms).

    Returns:
        bool :math:`(L,)`.
    """
    group = problem.label_group
    saved = problem.label_cost.copy()
    saved[group >= 0] += problem.group_cost[group[group >= 0]]
    return slack > saved


def _expand(problem: LabellingProblem, labels: np.ndarray, alpha: int) -> np.ndarray:
    """Best α-expansion of ``labels`` ignoring α's label cost, by one minimum cut (new array)."""
    layout = problem.layout
    if not np.any(labels != alpha):
        return labels.copy()
    compiled = kernel("expansion.move_terms")
    if compiled is None:
        terms = _move_terms(problem, labels, alpha)
    else:
        arrays = (
            layout.tail,
            layout.head,
            layout.weight,
            layout.graph_tail,
            layout.graph_head,
            layout.node_id,
        )
        terms = compiled(labels, alpha, problem.unary, *arrays)
    slack, counts, (pair_tail, pair_head, forward, backward), (movable, moving, to_alpha, to_keep) = terms

    retained = _retained_labels(problem, slack)
    charged = (counts > 0) & (problem.label_cost > 0) & ~retained
    charged[alpha] = False
    gadgets = [_gadget(problem.label_cost, charged, labels[layout.graph_order])]
    if len(problem.group_cost):
        # A group is charged as a label is: in use, not α's, without a label every optimal move keeps.
        group = problem.label_group
        in_use = (counts > 0) & (group >= 0)
        group_used = np.bincount(group[in_use], minlength=len(problem.group_cost)) > 0
        group_kept = np.bincount(group[in_use & retained], minlength=len(problem.group_cost)) > 0
        group_charged = group_used & (problem.group_cost > 0) & ~group_kept
        if group[alpha] >= 0:
            group_charged[group[alpha]] = False
        gadgets.append(_gadget(problem.group_cost, group_charged, group[labels[layout.graph_order]]))
    n_aux = sum(int(np.count_nonzero(n_groups)) + int(n_groups.sum()) for *_, n_groups in gadgets)
    n_arcs = sum(len(members) for _, _, members, _ in gadgets)

    graph = maxflow.Graph[float](len(labels) + n_aux, len(pair_tail) + n_arcs + n_aux)
    graph.add_nodes(len(labels))
    graph.add_edges(pair_tail, pair_head, forward, backward)
    graph.add_grid_tedges(moving, to_alpha, to_keep)
    for cost, owner, members, n_groups in gadgets:
        if len(members):
            _add_label_costs(graph, cost, owner, members, n_groups)
    graph.maxflow()

    expanded = labels.copy()
    expanded[movable[graph.get_grid_segments(moving)]] = alpha
    return expanded


def alpha_expansion(
    unary,
    edges,
    edge_weights=None,
    *,
    smoothness=1.0,
    label_cost=0.0,
    init_labels=None,
    max_cycles=2,
    outlier_cost=None,
    outlier_label_cost=0.0,
    label_groups=None,
    group_cost=None,
    rng=None,
) -> ExpansionResult:
    """Minimise data + Potts + label-cost energy by α-expansion (Boykov et al. 2001, Delong et al. 2012).

    Each cycle tries one α-expansion move per label (the outlier label last, or all in random order
    when ``rng`` is given); each move is the exact optimal expansion move and is kept only if it lowers
    :func:`labeling_energy`. At a converged labelling with non-negative data costs the energy is at most
    ``2 E_opt + sum(label costs)``.

    Args:
        unary: data costs :math:`(N, L)`, any real dtype; computed in float64.
        edges: integer node pairs :math:`(E, 2)`, each undirected edge listed once; duplicates add up;
            or a :class:`PottsGraph` (then ``edge_weights`` must be ``None``).
        edge_weights: non-negative :math:`(E,)`; ones by default.
        smoothness: non-negative Potts weight λ: an edge costs ``smoothness * w_e`` if its ends differ.
        label_cost: non-negative scalar or :math:`(L,)`, paid once for every label in use (MDL).
        init_labels: initial integer labels :math:`(N,)` in ``[0, L)`` or ``-1`` (outlier); by default
            the per-node minimum of ``unary`` (outlier column included).
        max_cycles: maximum number of expansion cycles; the loop stops earlier once a whole cycle
            changes nothing.
        outlier_cost: constant data cost of an extra outlier label, returned as ``-1``; ``None``
            for no outlier label.
        outlier_label_cost: label cost of the outlier label.
        label_groups: each label's group, integer :math:`(L,)` in ``[-1, G)`` (-1: in none), with
            ``group_cost``; ``None`` for no groups.
        group_cost: non-negative :math:`(G,)`, paid once for every group with a label in use (label
            subset costs).
        rng: ``None`` for the fixed label order, else a :class:`numpy.random.Generator` or seed for a
            random order in every cycle.

    Returns:
        :class:`ExpansionResult` with the labels, their energy, the energy history and the cycle count.

    Raises:
        ShapeError: an argument has the wrong shape.
        GraphCutError: negative weights or costs, NaN or inf, labels or node indices out of range.

    Example:
        >>> unary = np.array([[0.0, 2.0], [2.0, 0.0], [0.0, 2.0]])
        >>> alpha_expansion(unary, np.array([[0, 1], [1, 2]]), smoothness=3.0).labels
        array([0, 0, 0])
    """
    problem = prepare_problem(
        unary,
        edges,
        edge_weights,
        smoothness,
        label_cost,
        outlier_cost,
        outlier_label_cost,
        label_groups=label_groups,
        group_cost=group_cost,
    )
    max_cycles = check_integer(max_cycles, "max_cycles", error=GraphCutError)
    if init_labels is None:
        labels = np.argmin(problem.unary, axis=1)
    else:
        labels = internal_labels(init_labels, problem, "init_labels")
    generator = None if rng is None else np.random.default_rng(rng)

    energy = problem_energy(problem, labels)
    history = [energy]
    # Moves and changes are numbered (the initial labelling is change 1); a label needs a new attempt only
    # if the labelling changed after its last attempt.
    last_attempt = np.zeros(problem.n_labels, dtype=np.int64)
    last_change = 1 if len(labels) else 0
    move = 1
    n_cycles = 0
    while n_cycles < max_cycles and (last_attempt < last_change).any():
        order = np.arange(problem.n_labels) if generator is None else generator.permutation(problem.n_labels)
        for alpha in order:
            if last_attempt[alpha] >= last_change:
                continue
            move += 1
            last_attempt[alpha] = move
            candidate = _expand(problem, labels, int(alpha))
            if np.array_equal(candidate, labels):
                continue
            candidate_energy = problem_energy(problem, candidate)
            if candidate_energy < energy:
                labels, energy, last_change = candidate, candidate_energy, move
        n_cycles += 1
        history.append(energy)

    public = np.where(labels == problem.n_labels - 1, -1, labels) if problem.has_outlier else labels
    return ExpansionResult(public.astype(np.int64), energy, tuple(history), n_cycles)

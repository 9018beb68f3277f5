import importlib
import itertools

import numpy as np
import pytest

from evseg_torch.backend import using_backend
from evseg_torch.errors import EvsegError, ShapeError
from evseg_torch.graphcut import ExpansionResult, GraphCutError, alpha_expansion, labeling_energy
from evseg_torch.graphcut.alpha_expansion import _expand, _move_terms, _retained_labels
from evseg_torch.graphcut.problem import potts_graph, prepare_problem
from evseg_torch.pipeline import CascadedSegmenter
from evseg_torch.synthetic import make_scene

# The package re-exports the function under the module's name, so fetch the module itself.
alpha_expansion_module = importlib.import_module("evseg_torch.graphcut.alpha_expansion")


def _random_problem(rng, n_nodes, n_labels, n_edges):
    unary = rng.uniform(0.0, 3.0, size=(n_nodes, n_labels))
    edges = rng.integers(0, n_nodes, size=(n_edges, 2))
    weights = rng.uniform(0.0, 2.0, size=n_edges)
    return unary, edges, weights


def _all_energies(labelings, unary, edges, weights, smoothness, label_cost, outlier_cost, outlier_label_cost):
    """Energies of every row of ``labelings`` (K, N) by brute force, outlier = last column."""
    costs = np.broadcast_to(np.asarray(label_cost, dtype=float), unary.shape[1:])
    if outlier_cost is not None:
        unary = np.column_stack([unary, np.full(len(unary), outlier_cost)])
        costs = np.append(costs, outlier_label_cost)
    data = unary[np.arange(unary.shape[0]), labelings].sum(axis=1)
    potts = smoothness * (labelings[:, edges[:, 0]] != labelings[:, edges[:, 1]]) @ weights
    used = np.stack([(labelings == label).any(axis=1) for label in range(unary.shape[1])], axis=1)
    return data + potts + used @ costs


def _exhaustive_optimum(n_labels, *args):
    labelings = np.array(list(itertools.product(range(n_labels), repeat=args[0].shape[0])))
    return _all_energies(labelings, *args).min()


def _knn_edges(points, k):
    distance = np.linalg.norm(points[:, None] - points[None], axis=2)
    neighbours = np.argsort(distance, axis=1)[:, 1 : k + 1]
    edges = np.sort(np.stack([np.repeat(np.arange(len(points)), k), neighbours.ravel()], axis=1), axis=1)
    return np.unique(edges, axis=0)


class TestLabelingEnergy:
    def test_by_hand(self):
        unary = np.array([[1.0, 4.0], [2.0, 0.5], [3.0, 1.0]])
        edges = np.array([[0, 1], [1, 2], [0, 2], [0, 1]])
        weights = np.array([1.0, 2.0, 0.5, 1.0])
        labels = np.array([0, 1, 1])
        # data 1 + 0.5 + 1; Potts 2 * (1 + 0.5 + 1) over edges (0,1), (0,2), duplicated (0,1); labels 3 + 5.
        energy = labeling_energy(labels, unary, edges, weights, smoothness=2.0, label_cost=[3.0, 5.0])
        assert energy == pytest.approx(2.5 + 5.0 + 8.0)

    def test_outlier_label(self):
        unary = np.array([[1.0, 4.0], [2.0, 0.5], [3.0, 1.0]])
        edges = np.array([[0, 1], [1, 2]])
        energy = labeling_energy(
            np.array([-1, 1, -1]), unary, edges, label_cost=1.0, outlier_cost=0.25, outlier_label_cost=7.0
        )
        assert energy == pytest.approx(0.25 + 0.5 + 0.25 + 2.0 + 1.0 + 7.0)

    def test_matches_brute_force_formula(self):
        rng = np.random.default_rng(3)
        unary, edges, weights = _random_problem(rng, 6, 3, 10)
        labels = rng.integers(-1, 3, size=(20, 6))
        expected = _all_energies(
            np.where(labels < 0, 3, labels), unary, edges, weights, 1.5, [0.5, 1, 2], 0.7, 4
        )
        energies = [
            labeling_energy(
                row,
                unary,
                edges,
                weights,
                smoothness=1.5,
                label_cost=[0.5, 1, 2],
                outlier_cost=0.7,
                outlier_label_cost=4,
            )
            for row in labels
        ]
        np.testing.assert_allclose(energies, expected)


class TestExpansionMove:
    @pytest.mark.parametrize("group_size", [32, 2])
    @pytest.mark.parametrize("seed", range(12))
    def test_each_move_is_the_optimal_expansion(self, seed, group_size, monkeypatch):
        """The kept move (cut result or current labelling) is the best of all 2^n expansion moves.

        A group size of 2 splits every label-cost gadget into several group nodes.
        """
        monkeypatch.setattr(alpha_expansion_module, "_GROUP_SIZE", group_size)
        rng = np.random.default_rng(seed)
        n_nodes, n_labels = 7, 3
        unary, edges, weights = _random_problem(rng, n_nodes, n_labels, 12)
        unary -= 2.0 * (seed % 4 == 1)  # negative data costs are allowed
        label_cost = rng.uniform(0.0, 3.0, size=n_labels) * (seed % 3 != 0)
        outlier = (1.5 - 3.0 * (seed % 4 == 1), 2.0) if seed % 2 else (None, 0.0)
        args = (unary, edges, weights, 1.3, label_cost, *outlier)
        problem = prepare_problem(*args)
        start = rng.integers(0, problem.n_labels, size=n_nodes)
        for alpha, unused in itertools.product(range(problem.n_labels), [False, True]):
            # With α unused, its label cost is paid only if the move is taken.
            labels = np.where(start == alpha, (alpha + 1) % problem.n_labels, start) if unused else start
            movable = np.flatnonzero(labels != alpha)
            masks = np.array(list(itertools.product([False, True], repeat=len(movable))), dtype=bool)
            moves = np.tile(labels, (len(masks), 1))
            moves[:, movable] = np.where(masks, alpha, labels[movable])
            best = _all_energies(moves, *args).min()
            candidate = _expand(problem, labels, alpha)
            assert (candidate[candidate != labels] == alpha).all()
            kept = min(_all_energies(candidate[None], *args)[0], _all_energies(labels[None], *args)[0])
            assert kept == pytest.approx(best, abs=1e-9)


def _keep_every_gadget(problem, *args):
    """A stand-in for ``_retained_labels`` that retains no label: every label cost keeps its gadget."""
    return np.zeros(problem.n_labels, dtype=bool)


class TestRetainedLabels:
    """Labels that every optimal move keeps lose their label-cost gadget; that must change no result."""

    @staticmethod
    def _retained(problem, labels, alpha):
        return _retained_labels(problem, _move_terms(problem, labels, alpha)[0])

    @pytest.mark.parametrize("seed", range(20))
    def test_no_optimal_move_drops_a_retained_label(self, seed):
        rng = np.random.default_rng(seed)
        n_nodes, n_labels = 8, 3
        unary, edges, weights = _random_problem(rng, n_nodes, n_labels, 14)
        labels = rng.integers(0, n_labels, size=n_nodes)
        unary[np.arange(n_nodes), labels] -= rng.uniform(0.0, 3.0)  # labels supported by their data
        label_cost = rng.uniform(0.0, 4.0, size=n_labels)
        problem = prepare_problem(unary, edges, weights, 0.8, label_cost, None, 0.0)
        for alpha in range(n_labels):
            movable = np.flatnonzero(labels != alpha)
            masks = np.array(list(itertools.product([False, True], repeat=len(movable))), dtype=bool)
            moves = np.tile(labels, (len(masks), 1))
            moves[:, movable] = np.where(masks, alpha, labels[movable])
            # The cut's energy leaves out α's own label cost.
            without_alpha = np.where(np.arange(n_labels) == alpha, 0.0, label_cost)
            energies = _all_energies(moves, unary, edges, weights, 0.8, without_alpha, None, 0.0)
            best = moves[np.isclose(energies, energies.min(), rtol=0, atol=1e-9)]
            for label in np.flatnonzero(self._retained(problem, labels, alpha)):
                assert (best == label).any(axis=1).all()

    @pytest.mark.parametrize("seed", range(10))
    def test_same_result_as_with_every_gadget(self, seed, monkeypatch):
        rng = np.random.default_rng(seed)
        points = rng.uniform(0, 10, size=(400, 2))
        edges = _knn_edges(points, 6)
        truth = (points[:, 0] > 4) + 2 * (points[:, 1] > 6 - seed % 3)
        unary = rng.uniform(0, 1, size=(400, 5))
        unary[np.arange(400), truth] -= 0.5
        kwargs = dict(smoothness=0.3, label_cost=rng.uniform(1.0, 20.0, size=5), max_cycles=3, rng=seed)
        init = rng.integers(0, 5, size=400)
        calls = []

        def spy(*args):
            calls.append(retained(*args))
            return calls[-1]

        retained = alpha_expansion_module._retained_labels
        monkeypatch.setattr(alpha_expansion_module, "_retained_labels", spy)
        pruned = alpha_expansion(unary, edges, init_labels=init, **kwargs)
        monkeypatch.setattr(alpha_expansion_module, "_retained_labels", _keep_every_gadget)
        full = alpha_expansion(unary, edges, init_labels=init, **kwargs)
        assert any(r.any() for r in calls)  # the gadgets were dropped in some moves
        np.testing.assert_array_equal(pruned.labels, full.labels)
        assert pruned.energy_history == full.energy_history

    def test_same_result_on_a_real_window(self, monkeypatch):
        """Level two's labellings of a synthetic window, with and without dropping retained gadgets."""
        problems = []

        def record(unary, edges, **kwargs):
            problems.append((unary, edges, kwargs))
            return alpha_expansion(unary, edges, **kwargs)

        segmenter_module = importlib.import_module("evseg_torch.level_two.descent.segmenter")
        monkeypatch.setattr(segmenter_module, "alpha_expansion", record)
        CascadedSegmenter((90, 120))(make_scene((90, 120), n_objects=2, rng=3).events)
        assert problems
        dropped = 0
        for unary, graph, kwargs in problems:
            pruned = alpha_expansion(unary, graph, **kwargs)
            with monkeypatch.context() as patch:
                patch.setattr(alpha_expansion_module, "_retained_labels", _keep_every_gadget)
                full = alpha_expansion(unary, graph, **kwargs)
            np.testing.assert_array_equal(pruned.labels, full.labels)
            assert pruned.energy_history == full.energy_history
            problem = prepare_problem(
                unary, graph, None, kwargs["smoothness"], kwargs["label_cost"], None, 0.0
            )
            labels = (
                np.argmin(problem.unary, axis=1) if kwargs["init_labels"] is None else kwargs["init_labels"]
            )
            dropped += sum(self._retained(problem, labels, alpha).sum() for alpha in range(problem.n_labels))
        assert dropped > 0


class TestAlphaExpansion:
    def test_result_type_and_history(self):
        rng = np.random.default_rng(0)
        points = rng.uniform(0, 10, size=(300, 2))
        edges = _knn_edges(points, 6)
        unary = rng.uniform(0, 1, size=(300, 4))
        unary[np.arange(300), (points[:, 0] > 5) + 2 * (points[:, 1] > 5)] -= 0.4
        kwargs = dict(smoothness=0.4, label_cost=5.0, outlier_cost=0.9, outlier_label_cost=3.0)
        result = alpha_expansion(unary, edges, max_cycles=10, rng=1, **kwargs)
        assert isinstance(result, ExpansionResult)
        assert result.labels.dtype == np.int64 and result.labels.shape == (300,)
        assert len(result.energy_history) == result.n_cycles + 1
        assert np.all(np.diff(result.energy_history) <= 0)
        assert result.energy == result.energy_history[-1]
        assert result.energy == labeling_energy(result.labels, unary, edges, **kwargs)
        assert result.energy_history[0] == labeling_energy(np.argmin(unary, axis=1), unary, edges, **kwargs)
        assert result.energy < result.energy_history[0]

    @pytest.mark.parametrize("seed", range(15))
    def test_within_expansion_bound_of_exhaustive_optimum(self, seed):
        """Converged α-expansion with non-negative data costs satisfies E <= 2 E_opt + sum of label costs.

        (Summing the optimality of each expansion move towards the optimum's regions gives
        data + Potts <= E_data(opt) + 2 E_Potts(opt) + label costs of the optimum, and the labels that
        the result uses cost at most the sum of all label costs.)
        """
        rng = np.random.default_rng(seed)
        n_nodes, n_labels = int(rng.integers(4, 9)), int(rng.integers(2, 4))
        unary, edges, weights = _random_problem(rng, n_nodes, n_labels, 2 * n_nodes)
        label_cost = rng.uniform(0.0, 2.0, size=n_labels) * (seed % 2)
        smoothness = float(rng.uniform(0.2, 2.0))
        result = alpha_expansion(
            unary, edges, weights, smoothness=smoothness, label_cost=label_cost, max_cycles=50
        )
        optimum = _exhaustive_optimum(n_labels, unary, edges, weights, smoothness, label_cost, None, 0.0)
        assert result.energy >= optimum - 1e-9
        assert result.energy <= 2 * optimum + label_cost.sum() + 1e-9
        if not label_cost.any():
            assert result.energy <= 2 * optimum + 1e-9

    def test_potts_two_labels_is_exact(self):
        """With two labels and no label costs one expansion move is a full binary graph cut: optimal."""
        rng = np.random.default_rng(5)
        unary, edges, weights = _random_problem(rng, 8, 2, 16)
        result = alpha_expansion(unary, edges, weights, smoothness=0.8, max_cycles=5)
        optimum = _exhaustive_optimum(2, unary, edges, weights, 0.8, 0.0, None, 0.0)
        assert result.energy == pytest.approx(optimum)

    def test_label_cost_removes_duplicate_label(self):
        rng = np.random.default_rng(1)
        column = rng.uniform(0, 1, size=50)
        unary = np.column_stack([column, column, column + 0.5])
        edges = np.stack([np.arange(49), np.arange(1, 50)], axis=1)
        init = rng.integers(0, 2, size=50)
        without = alpha_expansion(unary, edges, smoothness=0.0, init_labels=init)
        assert set(without.labels) == {0, 1}
        result = alpha_expansion(unary, edges, smoothness=0.0, label_cost=1.0, init_labels=init)
        assert len(set(result.labels)) == 1 and result.labels[0] in (0, 1)

    def test_duplicated_models_collapse(self):
        """Three models for two motions (one of them duplicated with noise) end up as two labels."""
        rng = np.random.default_rng(2)
        points = rng.uniform(0, 10, size=(200, 2))
        truth = (points[:, 0] > 5).astype(int)
        residual_a = np.where(truth == 0, 0.1, 1.0) + rng.uniform(0, 0.2, size=200)
        residual_b = np.where(truth == 1, 0.1, 1.0) + rng.uniform(0, 0.2, size=200)
        residual_b2 = residual_b + rng.normal(0, 0.05, size=200)
        unary = np.column_stack([residual_a, residual_b, residual_b2])
        edges = _knn_edges(points, 5)
        init = np.argmin(unary, axis=1)
        assert len(set(init)) == 3
        result = alpha_expansion(unary, edges, smoothness=0.1, label_cost=10.0, max_cycles=5)
        assert len(set(result.labels)) == 2
        merged = np.where(result.labels == 2, 1, result.labels)
        assert (merged == truth).mean() > 0.95

    def test_outlier_label(self):
        rng = np.random.default_rng(4)
        truth = rng.integers(0, 2, size=60)
        unary = np.where(np.arange(2) == truth[:, None], 0.1, 1.0)
        gross = rng.choice(60, size=10, replace=False)
        unary[gross] = 5.0
        edges = np.empty((0, 2), dtype=int)
        result = alpha_expansion(unary, edges, label_cost=1.0, outlier_cost=2.0, outlier_label_cost=1.0)
        expected = truth.copy()
        expected[gross] = -1
        np.testing.assert_array_equal(result.labels, expected)
        plain = alpha_expansion(unary, edges, label_cost=1.0)
        assert (plain.labels >= 0).all()

    def test_outlier_init_labels(self):
        unary = np.array([[0.0, 1.0], [1.0, 0.0], [9.0, 9.0]])
        result = alpha_expansion(
            unary, np.array([[0, 1]]), init_labels=[-1, -1, -1], outlier_cost=3.0, smoothness=0.5
        )
        assert result.energy_history[0] == pytest.approx(9.0)
        np.testing.assert_array_equal(result.labels, [0, 1, -1])

    def test_smoothness_makes_chain_piecewise_constant(self):
        rng = np.random.default_rng(6)
        truth = np.repeat([0, 2, 1, 0], 50)
        unary = rng.uniform(0, 1, size=(200, 3))
        unary[np.arange(200), truth] -= 0.35
        edges = np.stack([np.arange(199), np.arange(1, 200)], axis=1)
        noisy = alpha_expansion(unary, edges, smoothness=0.0)
        assert np.count_nonzero(np.diff(noisy.labels)) > 20
        smooth = alpha_expansion(unary, edges, smoothness=1.5, max_cycles=5)
        assert np.count_nonzero(np.diff(smooth.labels)) == 3
        assert (smooth.labels == truth).mean() > 0.95

    def test_smoothness_denoises_grid(self):
        rng = np.random.default_rng(7)
        height, width = 30, 40
        truth = np.zeros((height, width), dtype=int)
        truth[5:20, 8:25] = 1
        truth[:, 30:] = 2
        unary = rng.uniform(0, 1, size=(height * width, 3))
        unary[np.arange(height * width), truth.ravel()] -= 0.3
        index = np.arange(height * width).reshape(height, width)
        edges = np.concatenate(
            [
                np.stack([index[:, :-1].ravel(), index[:, 1:].ravel()], axis=1),
                np.stack([index[:-1].ravel(), index[1:].ravel()], axis=1),
            ]
        )
        noisy = alpha_expansion(unary, edges, smoothness=0.0)
        result = alpha_expansion(unary, edges, smoothness=0.6, max_cycles=5, rng=0)
        assert (noisy.labels == truth.ravel()).mean() < 0.8
        assert (result.labels == truth.ravel()).mean() > 0.98
        assert np.all(np.diff(result.energy_history) <= 0)

    def test_init_labels_respected(self):
        unary = np.array([[0.0, 1.0], [1.0, 0.0]])
        edges = np.array([[0, 1]])
        init = np.array([1, 1])
        frozen = alpha_expansion(unary, edges, init_labels=init, max_cycles=0)
        np.testing.assert_array_equal(frozen.labels, init)
        assert frozen.n_cycles == 0 and frozen.energy_history == (frozen.energy,)
        # All-0 and all-1 tie under strong smoothness; the start decides, since ties are never accepted.
        kept = alpha_expansion(unary, edges, smoothness=5.0, init_labels=init, max_cycles=5)
        np.testing.assert_array_equal(kept.labels, [1, 1])
        assert kept.energy_history[0] == pytest.approx(1.0)
        default = alpha_expansion(unary, edges, smoothness=5.0, max_cycles=5)
        assert default.energy_history[0] == pytest.approx(5.0)
        np.testing.assert_array_equal(default.labels, [0, 0])

    def test_stops_when_a_cycle_changes_nothing(self):
        unary = np.array([[0.0, 1.0], [1.0, 0.0]])
        result = alpha_expansion(unary, np.array([[0, 1]]), smoothness=0.1, max_cycles=10)
        assert result.n_cycles == 1
        np.testing.assert_array_equal(result.labels, [0, 1])

    def test_random_order_is_reproducible(self):
        rng = np.random.default_rng(8)
        unary, edges, weights = _random_problem(rng, 100, 4, 300)
        first = alpha_expansion(unary, edges, weights, label_cost=1.0, rng=3, max_cycles=4)
        second = alpha_expansion(
            unary, edges, weights, label_cost=1.0, rng=np.random.default_rng(3), max_cycles=4
        )
        np.testing.assert_array_equal(first.labels, second.labels)
        assert first.energy_history == second.energy_history

    def test_does_not_modify_inputs(self):
        rng = np.random.default_rng(9)
        unary, edges, weights = _random_problem(rng, 40, 3, 80)
        label_cost = np.array([1.0, 2.0, 3.0])
        init = rng.integers(-1, 3, size=40)
        copies = [array.copy() for array in (unary, edges, weights, label_cost, init)]
        alpha_expansion(
            unary, edges, weights, label_cost=label_cost, init_labels=init, outlier_cost=1.0, max_cycles=3
        )
        labeling_energy(init, unary, edges, weights, label_cost=label_cost, outlier_cost=1.0)
        for original, copy in zip((unary, edges, weights, label_cost, init), copies, strict=True):
            np.testing.assert_array_equal(original, copy)

    def test_degenerate_sizes(self):
        empty = alpha_expansion(np.zeros((0, 3)), np.empty((0, 2), dtype=int))
        assert empty.labels.shape == (0,) and empty.energy == 0.0
        single = alpha_expansion(np.array([[2.0], [1.0]]), np.array([[0, 1], [1, 1]]), label_cost=0.5)
        np.testing.assert_array_equal(single.labels, [0, 0])
        assert single.energy == pytest.approx(3.5)
        integer = alpha_expansion(np.array([[2, 0], [0, 2]]), np.array([[0, 1]]), smoothness=3)
        assert integer.energy == pytest.approx(2.0)


class TestGroupCosts:
    """Label subset costs: a group pays once when any of its labels is in use."""

    @staticmethod
    def _energies(moves, unary, edges, weights, smoothness, label_cost, groups, group_cost):
        used = np.stack([(moves == label).any(axis=1) for label in range(unary.shape[1])], axis=1)
        group_used = np.stack([used[:, groups == g].any(axis=1) for g in range(len(group_cost))], axis=1)
        return (
            _all_energies(moves, unary, edges, weights, smoothness, label_cost, None, 0.0)
            + group_used @ group_cost
        )

    @pytest.mark.parametrize("group_size", [32, 2])
    @pytest.mark.parametrize("seed", range(12))
    def test_each_move_is_the_optimal_expansion(self, seed, group_size, monkeypatch):
        monkeypatch.setattr(alpha_expansion_module, "_GROUP_SIZE", group_size)
        rng = np.random.default_rng(seed)
        n_nodes, n_labels = 7, 4
        unary, edges, weights = _random_problem(rng, n_nodes, n_labels, 12)
        label_cost = rng.uniform(0.0, 2.0, size=n_labels)
        groups = np.array([-1, 0, 0, 1]) if seed % 2 else np.array([0, 0, 0, -1])
        group_cost = rng.uniform(0.0, 6.0, size=groups.max() + 1)
        args = (unary, edges, weights, 1.3, label_cost, groups, group_cost)
        problem = prepare_problem(*args[:5], None, 0.0, label_groups=groups, group_cost=group_cost)
        start = rng.integers(0, n_labels, size=n_nodes)
        for alpha, unused in itertools.product(range(n_labels), [False, True]):
            labels = np.where(start == alpha, (alpha + 1) % n_labels, start) if unused else start
            movable = np.flatnonzero(labels != alpha)
            masks = np.array(list(itertools.product([False, True], repeat=len(movable))), dtype=bool)
            moves = np.tile(labels, (len(masks), 1))
            moves[:, movable] = np.where(masks, alpha, labels[movable])
            best = self._energies(moves, *args).min()
            candidate = _expand(problem, labels, alpha)
            kept = min(self._energies(np.stack([candidate, labels]), *args))
            assert kept == pytest.approx(best, abs=1e-9)

    @pytest.mark.parametrize("seed", range(5))
    def test_energy_is_the_labellings_and_never_rises(self, seed):
        rng = np.random.default_rng(seed)
        unary, edges, weights = _random_problem(rng, 30, 5, 60)
        kwargs = dict(
            smoothness=0.5,
            label_cost=rng.uniform(0, 1, 5),
            label_groups=np.array([-1, 0, 0, 0, 1]),
            group_cost=np.array([4.0, 2.0]),
        )
        result = alpha_expansion(unary, edges, weights, max_cycles=5, **kwargs)
        assert result.energy == pytest.approx(labeling_energy(result.labels, unary, edges, weights, **kwargs))
        assert all(b <= a for a, b in zip(result.energy_history, result.energy_history[1:], strict=False))

    def test_a_shared_cost_keeps_two_labels_of_a_group(self):
        # Two blocks of nodes, each best in its own label by 6; the labels cost 7 each alone, 6 + 1 each
        # in one group.
        unary = np.array([[0.0, 3.0], [0.0, 3.0], [3.0, 0.0], [3.0, 0.0]])
        edges = np.array([[0, 1], [2, 3]])
        alone = alpha_expansion(unary, edges, label_cost=7.0, init_labels=[0, 0, 0, 0])
        assert alone.labels.tolist() == [0, 0, 0, 0]  # the second label does not pay its 7
        shared = alpha_expansion(
            unary, edges, label_cost=1.0, label_groups=[0, 0], group_cost=[6.0], init_labels=[0, 0, 0, 0]
        )
        assert shared.labels.tolist() == [0, 0, 1, 1]

    def test_no_groups_is_the_plain_energy(self):
        rng = np.random.default_rng(3)
        unary, edges, weights = _random_problem(rng, 40, 4, 80)
        kwargs = dict(smoothness=0.4, label_cost=rng.uniform(0, 3, 4), max_cycles=4)
        plain = alpha_expansion(unary, edges, weights, **kwargs)
        ungrouped = alpha_expansion(
            unary, edges, weights, label_groups=np.full(4, -1), group_cost=np.zeros(0), **kwargs
        )
        np.testing.assert_array_equal(plain.labels, ungrouped.labels)
        assert plain.energy_history == ungrouped.energy_history


class TestValidation:
    UNARY = np.zeros((3, 2))
    EDGES = np.array([[0, 1], [1, 2]])

    @pytest.mark.parametrize(
        ("kwargs", "error", "match"),
        [
            (dict(unary=np.zeros(3)), ShapeError, "unary must have shape"),
            (dict(unary=np.zeros((3, 0))), ShapeError, "unary must have shape"),
            (dict(unary=np.array([[0.0, np.nan]] * 3)), GraphCutError, "unary must be finite"),
            (dict(unary=np.full((3, 2), "a")), GraphCutError, "unary must hold real numbers"),
            (dict(edges=np.array([0, 1])), ShapeError, "edges must have shape"),
            (dict(edges=np.array([[0.0, 1.0]])), GraphCutError, "edges must be an integer array"),
            (dict(edges=np.array([[0, 3]])), GraphCutError, r"edges must index nodes in \[0, 3\)"),
            (dict(edges=np.array([[-1, 0]])), GraphCutError, "edges must index nodes"),
            (dict(edge_weights=np.ones(3)), ShapeError, "edge_weights must have shape"),
            (dict(edge_weights=np.array([1.0, -1.0])), GraphCutError, "edge_weights must be non-negative"),
            (dict(edge_weights=np.array([1.0, np.nan])), GraphCutError, "edge_weights must be finite"),
            (dict(smoothness=-1.0), GraphCutError, "smoothness must be non-negative"),
            (dict(smoothness=np.ones(2)), ShapeError, "smoothness must be a scalar"),
            (dict(label_cost=-1.0), GraphCutError, "label_cost must be non-negative"),
            (dict(label_cost=np.ones(3)), ShapeError, "label_cost must be a scalar or have shape"),
            (dict(label_cost=np.inf), GraphCutError, "label_cost must be finite"),
            (dict(outlier_cost=np.nan), GraphCutError, "outlier_cost must be finite"),
            (
                dict(outlier_cost=1.0, outlier_label_cost=-2.0),
                GraphCutError,
                "outlier_label_cost must be non",
            ),
            (dict(init_labels=[0, 1]), ShapeError, r"init_labels must have shape \(3,\)"),
            (dict(init_labels=[0, 2, 1]), GraphCutError, r"init_labels must lie in \[0, 2\)"),
            (dict(init_labels=[0, -1, 1]), GraphCutError, "-1 only with outlier_cost"),
            (
                dict(init_labels=[0, -2, 1], outlier_cost=1.0),
                GraphCutError,
                r"init_labels must lie in \[-1, 2\)",
            ),
            (dict(init_labels=[0.0, 1.0, 1.0]), GraphCutError, "init_labels must be an integer array"),
            (dict(max_cycles=-1), GraphCutError, "max_cycles must be an integer of at least 0"),
            (dict(max_cycles=1.5), GraphCutError, "max_cycles must be an integer of at least 0"),
            (dict(label_groups=[0, 0]), GraphCutError, "label_groups and group_cost go together"),
            (dict(label_groups=[0], group_cost=[1.0]), ShapeError, r"label_groups must have shape \(2,\)"),
            (
                dict(label_groups=[0, 1], group_cost=[1.0]),
                GraphCutError,
                r"label_groups must lie in \[-1, 1\)",
            ),
            (dict(label_groups=[0, 0], group_cost=[-1.0]), GraphCutError, "group_cost must be non-negative"),
            (dict(label_groups=[0, 0], group_cost=[[1.0]]), ShapeError, "group_cost must have shape"),
        ],
    )
    def test_invalid_inputs(self, kwargs, error, match):
        arguments = dict(unary=self.UNARY, edges=self.EDGES) | kwargs
        with pytest.raises(error, match=match) as info:
            alpha_expansion(**arguments)
        assert isinstance(info.value, EvsegError) and isinstance(info.value, ValueError)

    def test_labeling_energy_validates_labels(self):
        with pytest.raises(GraphCutError, match=r"labels must lie in \[0, 2\)"):
            labeling_energy([0, 5, 1], self.UNARY, self.EDGES)
        with pytest.raises(ShapeError, match=r"labels must have shape \(3,\)"):
            labeling_energy([[0, 1, 1]], self.UNARY, self.EDGES)


class TestPottsGraph:
    def test_reused_graph_matches_edge_arrays(self):
        rng = np.random.default_rng(3)
        unary, edges, weights = _random_problem(rng, 40, 3, 120)
        graph = potts_graph(edges, weights, n_nodes=40)
        assert graph.n_nodes == 40 and graph.n_edges <= len(edges)
        for smoothness in (0.0, 0.7, 2.0):
            energy = {"smoothness": smoothness, "label_cost": 1.5}
            direct = alpha_expansion(unary, edges, weights, **energy)
            for reused in (
                alpha_expansion(unary, graph, **energy),
                alpha_expansion(unary, potts_graph(edges, weights, n_nodes=40, reorder=False), **energy),
            ):
                np.testing.assert_array_equal(reused.labels, direct.labels)
                assert reused.energy == pytest.approx(direct.energy)
            assert labeling_energy(direct.labels, unary, graph, **energy) == pytest.approx(direct.energy)

    def test_rejects_mismatches(self):
        graph = potts_graph(np.array([[0, 1]]), n_nodes=2)
        with pytest.raises(ShapeError, match="2 nodes"):
            alpha_expansion(np.zeros((3, 2)), graph)
        with pytest.raises(GraphCutError, match="edge_weights must be None"):
            alpha_expansion(np.zeros((2, 2)), graph, np.ones(1))
        with pytest.raises(GraphCutError, match="n_nodes"):
            potts_graph(np.array([[0, 1]]), n_nodes=-1)
        with pytest.raises(GraphCutError, match="index nodes"):
            potts_graph(np.array([[0, 5]]), n_nodes=2)


class TestCompiledMoves:
    """Where Numba is installed, each move's graph comes from expansion_kernel: the same arrays, byte for
    byte (a sum taken in another order shows up as a different byte)."""

    @pytest.mark.parametrize("seed", range(6))
    def test_move_terms_equal_numpy(self, seed):
        kernel = pytest.importorskip("evseg_torch.kernels.expansion")
        rng = np.random.default_rng(seed)
        points = rng.uniform(0, 10, size=(300, 2))
        unary = rng.uniform(-1, 5, size=(300, 4))
        outlier = (2.0, 1.0) if seed % 2 else (None, 0.0)
        problem = prepare_problem(
            unary, _knn_edges(points, 5), None, 0.7, rng.uniform(0, 9, size=4), *outlier
        )
        layout = problem.layout
        labels = rng.integers(0, problem.n_labels - 1, size=300)  # the last label unused
        edges = (layout.tail, layout.head, layout.weight, layout.graph_tail, layout.graph_head)
        for alpha in range(problem.n_labels):
            found = kernel.move_terms(labels, alpha, problem.unary, *edges, layout.node_id)
            expected = _move_terms(problem, labels, alpha)
            for got, want in zip(_flat(found), _flat(expected), strict=True):
                assert got.dtype == want.dtype and got.tobytes() == want.tobytes()

    def test_labellings_equal_numpy(self):
        pytest.importorskip("numba")
        rng = np.random.default_rng(5)
        points = rng.uniform(0, 10, size=(500, 2))
        unary = rng.uniform(0, 1, size=(500, 5))
        kwargs = dict(smoothness=0.4, label_cost=rng.uniform(1.0, 20.0, size=5), max_cycles=3, rng=1)
        compiled = alpha_expansion(unary, _knn_edges(points, 6), **kwargs)
        with using_backend("torch"):
            numpy = alpha_expansion(unary, _knn_edges(points, 6), **kwargs)
        np.testing.assert_array_equal(compiled.labels, numpy.labels)
        assert compiled.energy_history == numpy.energy_history


def _flat(terms):
    """The arrays of a move's terms, nested tuples flattened."""
    for item in terms:
        yield from _flat(item) if isinstance(item, tuple) else [np.asarray(item)]

import itertools

import numpy as np
import pytest

from evseg_torch.errors import ConfigError, ModelError, ShapeError
from evseg_torch.level_one.gc_ransac import (
    QUALITIES,
    Correspondences,
    gc_ransac,
    graph_cut_inliers,
    iteration_bound,
    preference,
)
from evseg_torch.level_one.neighborhood import adjacency, neighborhood_graph
from evseg_torch.motion import Affine4, Translation
from tests.helpers.level_one import DT, SENSOR, make_scene


class TestNeighborhood:
    def test_matches_brute_force(self):
        points = np.random.default_rng(0).uniform(0, 60, (80, 2))
        edges = neighborhood_graph(points, 9.0)
        distance = np.linalg.norm(points[:, None] - points[None], axis=-1)
        expected = np.argwhere(np.triu(distance <= 9.0, k=1))
        np.testing.assert_array_equal(edges, expected)
        assert edges.dtype == np.int64

    def test_adjacency_lists_both_directions(self):
        edges = np.array([[0, 1], [0, 2], [2, 3]])
        indptr, indices = adjacency(edges, 5)
        neighbours = [sorted(indices[indptr[i] : indptr[i + 1]].tolist()) for i in range(5)]
        assert neighbours == [[1, 2], [0], [0, 3], [2], []]

    def test_exception(self):
        with pytest.raises(ShapeError):
            neighborhood_graph(np.zeros((3, 3)), 1.0)
        with pytest.raises(ConfigError):
            neighborhood_graph(np.zeros((3, 2)), 0.0)


class TestNapsac:
    @pytest.mark.parametrize("model", [Translation(SENSOR), Affine4(SENSOR)])
    def test_samples_are_distinct_neighbours(self, model):
        _, src, dst, dt, _, _ = make_scene(0, "affine4", 2)
        data = Correspondences.build(src, dst, dt, model)
        samples = data.napsac(np.random.default_rng(0), 500)
        assert samples.shape == (500, model.min_samples)
        linked = {tuple(edge) for edge in data.edges.tolist()}
        for centre, *others in samples.tolist():
            assert all((min(centre, o), max(centre, o)) in linked for o in others)

    def test_weights_steer_samples_to_unexplained_points(self):
        model, src, dst, dt, truth, _ = make_scene(0, "affine4", 3)
        data = Correspondences.build(src, dst, dt, model)
        weights = np.where(truth == 2, 1.0, 0.05)  # object 2 unexplained, the rest explained
        samples = data.napsac(np.random.default_rng(1), 4000, weights)
        linked = {tuple(edge) for edge in data.edges.tolist()}
        assert all((min(a, b), max(a, b)) in linked and a != b for a, b in samples.tolist())
        eligible = data.degree >= 1
        expected = weights[eligible & (truth == 2)].sum() / weights[eligible].sum()
        assert np.mean(truth[samples[:, 0]] == 2) == pytest.approx(expected, abs=0.03)
        # Neighbours too: most samples centred on object 2 stay on it.
        on_object = samples[truth[samples[:, 0]] == 2]
        assert np.mean(truth[on_object[:, 1]] == 2) > 0.9


class TestGraphCut:
    def _energy(self, labels, ratio, edges, weight):
        inside = ratio < 1
        unary = np.where(
            labels,
            np.where(inside, 0.0, (1 - weight) * ratio),
            np.where(inside, (1 - weight) * (1 - ratio), 0.0),
        ).sum()
        d = np.minimum(ratio, 1.0)
        i, j = edges.T
        pair = np.where(
            labels[i] != labels[j],
            weight,
            np.where(~labels[i] & ~labels[j], 0.5 * weight * (d[i] + d[j]), 0.0),
        )
        return unary + pair.sum()

    def test_exact_minimum(self):
        rng = np.random.default_rng(1)
        for _ in range(5):
            sq = rng.uniform(0, 2, 9) ** 2 * 5.0625
            edges = np.array([e for e in itertools.combinations(range(9), 2) if rng.random() < 0.4])
            found = graph_cut_inliers(sq, edges, threshold=1.5, spatial_coherence_weight=0.3)
            ratio = sq / 5.0625
            best = min(
                self._energy(np.array(bits, dtype=bool), ratio, edges, 0.3)
                for bits in itertools.product([False, True], repeat=9)
            )
            assert self._energy(found, ratio, edges, 0.3) == pytest.approx(best)

    def test_zero_weight_is_thresholding(self):
        sq = np.random.default_rng(0).uniform(0, 10, 50)
        edges = neighborhood_graph(np.random.default_rng(1).uniform(0, 20, (50, 2)), 5.0)
        found = graph_cut_inliers(sq, edges, threshold=1.5, spatial_coherence_weight=0.0)
        np.testing.assert_array_equal(found, sq < 1.5**2 * 2.25)

    def test_improves_on_thresholding(self):
        # A dense object with heavier noise (1 px) amid background and outliers: ~8% of its tracks
        # exceed the truncated threshold, and their many neighbours vouch for them.
        model, src, dst, dt, truth, params = make_scene(0, "affine4", 2, n_object=80, noise=1.0)
        sq = model.residuals(params[1], src, dst, dt) ** 2
        edges = neighborhood_graph(dst, 15.0)
        truth = truth == 1

        def f1(found):
            hits = np.count_nonzero(found & truth)
            return 2 * hits / (np.count_nonzero(found) + np.count_nonzero(truth))

        thresholded = graph_cut_inliers(sq, edges, threshold=1.5, spatial_coherence_weight=0.0)
        labelled = graph_cut_inliers(sq, edges, threshold=1.5, spatial_coherence_weight=0.14)
        assert np.count_nonzero(labelled & truth) > np.count_nonzero(thresholded & truth)
        assert f1(labelled) > f1(thresholded)


class TestGCRansac:
    @pytest.mark.parametrize("name", ["translation", "affine4"])
    def test_single_model_half_outliers(self, name):
        model, src, dst, dt, truth, params = make_scene(3, name, 1, n_background=150, outlier_ratio=0.5)
        assert np.mean(truth == -1) == pytest.approx(0.5)
        found, inliers, n_iterations = gc_ransac(src, dst, dt, model, threshold=1.5, rng=0)
        errors = np.linalg.norm(model.predict(src, DT, found) - model.predict(src, DT, params[0]), axis=1)
        assert errors.max() < 0.5
        assert np.all(inliers[truth == 0])
        assert np.mean(inliers[truth == -1]) < 0.15
        assert 20 <= n_iterations <= 1000

    @pytest.mark.parametrize("quality", QUALITIES)
    def test_compound_preference_proposes_unexplained_motion(self, quality):
        model, src, dst, dt, truth, params = make_scene(0, "affine4", 2)
        background = preference(model.residuals(params[0], src, dst, dt) ** 2, 1.5)
        found, inliers, _ = gc_ransac(
            src, dst, dt, model, compound_preference=background, quality=quality, rng=0
        )
        errors = np.linalg.norm(model.predict(src, DT, found) - model.predict(src, DT, params[1]), axis=1)
        assert errors[truth == 1].max() < 0.5
        assert np.all(inliers[truth == 1]) and not inliers[truth == 0].any()

    def test_same_seed_same_result(self):
        model, src, dst, dt, _, _ = make_scene(0, "affine4", 3)
        first = gc_ransac(src, dst, dt, model, rng=3)
        second = gc_ransac(src, dst, dt, model, rng=np.random.default_rng(3))
        np.testing.assert_array_equal(first[0], second[0])
        np.testing.assert_array_equal(first[1], second[1])
        assert first[2] == second[2]

    def test_neighbors_argument(self):
        model, src, dst, dt, _, _ = make_scene(0, "translation", 1)
        edges = neighborhood_graph(dst, 15.0)
        by_radius = gc_ransac(src, dst, dt, model, neighborhood_ball_radius=15.0, rng=0)
        by_graph = gc_ransac(src, dst, dt, model, neighbors=edges, rng=0)
        np.testing.assert_array_equal(by_radius[0], by_graph[0])

    def test_too_few_points(self):
        found, inliers, n_iterations = gc_ransac(np.zeros((1, 2)), np.ones((1, 2)), 0.01, Affine4(SENSOR))
        assert found is None and inliers.shape == (1,) and not inliers.any() and n_iterations == 0

    def test_exception(self):
        model, src, dst, dt, _, _ = make_scene(0, "translation", 1)
        with pytest.raises(ModelError, match="src and dst"):
            gc_ransac(src, dst[:-1], dt, model)
        with pytest.raises(ModelError, match="NaN"):
            gc_ransac(np.where(np.arange(len(src))[:, None] == 0, np.nan, src), dst, dt, model)
        with pytest.raises(ConfigError, match="conf"):
            gc_ransac(src, dst, dt, model, conf=1.0)
        with pytest.raises(ConfigError, match="min_iters"):
            gc_ransac(src, dst, dt, model, max_iters=10, min_iters=20)
        with pytest.raises(ShapeError, match="neighbors"):
            gc_ransac(src, dst, dt, model, neighbors=np.array([[0, len(src)]]))
        with pytest.raises(ShapeError, match="compound_preference"):
            gc_ransac(src, dst, dt, model, compound_preference=np.ones(3))


def test_iteration_bound():
    assert iteration_bound(0.5, 2, 0.95) == pytest.approx(np.log(0.05) / np.log(0.75))
    assert iteration_bound(1.0, 2, 0.95) == 0.0
    assert iteration_bound(0.0, 2, 0.95) == float("inf")

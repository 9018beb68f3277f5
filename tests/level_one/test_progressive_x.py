import itertools

import numpy as np
import pytest

from evseg_torch.config import LevelOneConfig
from evseg_torch.errors import ConfigError, ModelError
from evseg_torch.graphcut.problem import labeling_energy
from evseg_torch.level_one.gc_ransac import Correspondences
from evseg_torch.level_one.progressive_x import (
    OUTLIER,
    ProgressiveXResult,
    _pearl_unary,
    pearl,
    progressive_x,
)
from evseg_torch.motion import Affine4, Translation
from tests.helpers.level_one import AFFINE, ALONE, DT, SENSOR, make_scene


def match(result: ProgressiveXResult, truth: np.ndarray, n_motions: int) -> np.ndarray:
    """The recovered label holding most points of each true motion (-1 if none)."""
    matched = np.full(n_motions, -1)
    for k in range(n_motions):
        found = result.labels[(truth == k) & (result.labels >= 0)]
        if found.size:
            matched[k] = np.bincount(found).argmax()
    return matched


def displacement_errors(model, src, params_true, params_found) -> np.ndarray:
    """Difference in predicted displacement over DT at ``src``, px."""
    return np.linalg.norm(model.predict(src, DT, params_found) - model.predict(src, DT, params_true), axis=1)


class TestRecovery:
    @pytest.mark.parametrize("quality", ["progressive_x", "paper"])
    @pytest.mark.parametrize("name", ["translation", "affine4"])
    @pytest.mark.parametrize("n_motions", [1, 2, 3, 4])
    def test_recovers_motions(self, name, n_motions, quality):
        model, src, dst, dt, truth, params = make_scene(n_motions, name, n_motions)
        result = progressive_x(src, dst, dt, model, quality=quality, rng=0, **ALONE)
        assert result.params.shape == (n_motions, model.n_params)
        assert result.labels.dtype == np.int64 and result.labels.shape == truth.shape
        matched = match(result, truth, n_motions)
        assert sorted(matched.tolist()) == list(range(n_motions))  # one instance per motion
        for k, label in enumerate(matched):
            own = truth == k
            errors = displacement_errors(model, src[own], params[k], result.params[label])
            # 0.3 px noise; the truncated quality (threshold 2.25 px) lets a model bend towards outliers
            # near it, hence a looser bound on the worst point than on the RMS.
            assert np.sqrt(np.mean(errors**2)) < 0.5
            assert errors.max() < 1.2
            assert np.mean(result.labels[own] == label) >= 0.95

    def test_outlier_sentinel(self):
        model, src, dst, dt, truth, _ = make_scene(0, "affine4", 2)
        result = progressive_x(src, dst, dt, model, rng=0, **ALONE)
        assert OUTLIER == -1
        assert set(np.unique(result.labels)) <= {-1, 0, 1}
        # Most gross outliers stay unexplained (some coincide with a motion or are smoothed into one).
        assert np.mean(result.labels[truth == -1] == OUTLIER) > 0.5

    def test_no_spurious_models(self):
        exact = 0
        for seed in range(10):
            model, src, dst, dt, _, _ = make_scene(100 + seed, "affine4", 2)
            exact += len(progressive_x(src, dst, dt, model, rng=seed, **ALONE).params) == 2
        assert exact >= 9

    def test_same_seed_same_result(self):
        model, src, dst, dt, _, _ = make_scene(3, "affine4", 3)
        first = progressive_x(src, dst, dt, model, rng=7, **ALONE)
        second = progressive_x(src, dst, dt, model, rng=np.random.default_rng(7), **ALONE)
        np.testing.assert_array_equal(first.params, second.params)
        np.testing.assert_array_equal(first.labels, second.labels)
        assert (first.n_proposals, first.n_iterations) == (second.n_proposals, second.n_iterations)

    def test_inputs_not_mutated(self):
        model, src, dst, dt, _, _ = make_scene(0, "translation", 2)
        copies = [src.copy(), dst.copy(), dt.copy()]
        initial = np.array([[60.0, -30.0]])
        progressive_x(src, dst, dt, model, initial_models=initial, rng=0, **ALONE)
        for before, after in zip(copies, [src, dst, dt], strict=True):
            np.testing.assert_array_equal(before, after)
        np.testing.assert_array_equal(initial, [[60.0, -30.0]])

    def test_maximum_model_number(self):
        model, src, dst, dt, _, _ = make_scene(0, "affine4", 3)
        result = progressive_x(src, dst, dt, model, maximum_model_number=1, rng=0, **ALONE)
        assert len(result.params) == 1 and result.n_proposals == 1


class TestCloseMotions:
    """Two adjacent objects whose motions differ by 6-9 px over a 30 ms window, with 8 or 12 tracks each.

    Discs of radius 20 px, centres 45 px apart, moving 250 px/s apart (7.5 px over the window) and
    rotating at +-1 rad/s about their centres, each 6.3-6.6 px from the background over the window;
    the tracks span 20 ms (the middle of a window's first and last thirds). One affine4 instance fits
    both objects to about 1.2 px (median), and PEARL's Potts term then labels every track: stopping on
    PEARL's outliers (Progressive-X's ``N - N_C``) kept the objects apart in 10 of these 20 scenes.
    """

    CENTRES = np.array([[100.0, 90.0], [145.0, 90.0]])

    @staticmethod
    def about(model, centre, velocity, rotation):
        """Affine4 parameters of a rotation at ``rotation`` rad/s about ``centre`` moving at ``velocity``."""
        offset = np.asarray(model.principal_point) - centre
        return np.array(
            [velocity[0] - rotation * offset[1], velocity[1] + rotation * offset[0], 0.0, rotation]
        )

    def test_close_objects_get_instances_of_their_own(self):
        model = Affine4(SENSOR)
        params = np.array(
            [
                AFFINE[0],
                self.about(model, self.CENTRES[0], [-110.0, 95.0], 1.0),
                self.about(model, self.CENTRES[1], [-110.0, -155.0], -1.0),
            ]
        )
        one = LevelOneConfig()
        separated = 0
        for n_object, seed in itertools.product([8, 12], range(10)):
            model, src, dst, dt, truth, _ = make_scene(
                seed,
                "affine4",
                3,
                n_background=150,
                n_object=n_object,
                outlier_ratio=0.0,
                radius=20.0,
                params=params,
                centres=self.CENTRES,
                dt=0.02,
            )
            result = progressive_x(
                src,
                dst,
                dt,
                model,
                threshold=one.threshold,
                minimum_point_number=one.minimum_point_number,
                rng=seed,
            )
            matched = match(result, truth, 3)
            held = [np.mean(result.labels[truth == k] == label) for k, label in enumerate(matched)]
            separated += len(set(matched.tolist())) == 3 and min(held) >= 0.8
            assert len(result.params) <= 4
        assert separated >= 17


class TestReuse:
    def test_reuse_gives_same_models_with_fewer_iterations(self):
        model, src, dst, dt, truth, params = make_scene(1, "affine4", 3)
        cold = progressive_x(src, dst, dt, model, rng=0, **ALONE)
        # The next window: same motions, new tracks, noise and outliers.
        model, src, dst, dt, truth, params = make_scene(2, "affine4", 3)
        fresh = progressive_x(src, dst, dt, model, rng=0, **ALONE)
        reused = progressive_x(src, dst, dt, model, initial_models=cold.params, rng=0, **ALONE)
        assert len(reused.params) == 3
        # Only the final proposal, which confirms that nothing is left to find, remains to be sampled.
        assert reused.n_iterations < fresh.n_iterations
        assert reused.n_proposals < fresh.n_proposals
        matched = match(reused, truth, 3)
        for k, label in enumerate(matched):
            errors = displacement_errors(model, src[truth == k], params[k], reused.params[label])
            assert np.sqrt(np.mean(errors**2)) < 0.5
            assert np.mean(reused.labels[truth == k] == label) >= 0.95

    def test_stale_model_dropped_and_new_motion_found(self):
        model, src, dst, dt, truth, params = make_scene(4, "affine4", 3)
        stale = np.array([[-400.0, 400.0, 0.0, 0.0]])
        # The background and a motion that has left the scene are known; object 2 is new.
        result = progressive_x(
            src, dst, dt, model, initial_models=np.concatenate([params[:1], stale]), rng=0, **ALONE
        )
        assert len(result.params) == 3
        matched = match(result, truth, 3)
        assert sorted(matched.tolist()) == [0, 1, 2]
        assert matched[0] == 0  # historical models keep their order


class TestPearl:
    def test_energy_not_above_initial_labelling(self):
        model, src, dst, dt, _, params = make_scene(5, "affine4", 3)
        data = Correspondences.build(src, dst, dt, model)
        # Perturbed instances plus a duplicate of the background.
        start = np.concatenate([params + np.array([3.0, -2.0, 0.01, 0.0]), params[:1]])
        energy = dict(smoothness=0.14, label_cost=10.0, outlier_cost=0.86, outlier_label_cost=10.0)
        unary = _pearl_unary(data, start, 1.5, 0.14)
        labels_start = np.where(np.min(unary, axis=1) < 0.86, np.argmin(unary, axis=1), OUTLIER)
        before = labeling_energy(labels_start, unary, data.edges, **energy)
        found, labels = pearl(
            data,
            start,
            labels_start,
            threshold=1.5,
            spatial_coherence_weight=0.14,
            label_cost=10.0,
            min_inliers=10,
        )
        after = labeling_energy(labels, _pearl_unary(data, found, 1.5, 0.14), data.edges, **energy)
        assert after <= before + 1e-9
        assert len(found) == 3  # the duplicate is merged away by the label cost


class TestErrors:
    def test_shape_mismatch(self):
        model = Translation(SENSOR)
        with pytest.raises(ModelError, match="src and dst"):
            progressive_x(np.zeros((5, 2)), np.zeros((4, 2)), 0.01, model)
        with pytest.raises(ModelError, match="dt"):
            progressive_x(np.zeros((5, 2)), np.zeros((5, 2)), np.full(3, 0.01), model)

    def test_bad_values(self):
        model, src, dst, dt, _, _ = make_scene(0, "translation", 1)
        with pytest.raises(ModelError, match="non-zero"):
            progressive_x(src, dst, np.zeros_like(dt), model)
        with pytest.raises(ConfigError, match="threshold"):
            progressive_x(src, dst, dt, model, threshold=0.0)
        with pytest.raises(ConfigError, match="tanimoto"):
            progressive_x(src, dst, dt, model, maximum_tanimoto_similarity=1.5)
        with pytest.raises(ModelError, match="initial_models"):
            progressive_x(src, dst, dt, model, initial_models=np.zeros((1, 4)))
        with pytest.raises(ModelError, match="MotionModel"):
            progressive_x(src, dst, dt, "translation")

    def test_too_few_points_give_empty_result(self):
        model, src, dst, dt, _, _ = make_scene(0, "affine4", 1)
        result = progressive_x(src[:5], dst[:5], dt[:5], model, **ALONE)
        assert result.params.shape == (0, 4)
        np.testing.assert_array_equal(result.labels, np.full(5, OUTLIER))
        assert (result.n_proposals, result.n_iterations) == (0, 0)
        empty = progressive_x(np.zeros((0, 2)), np.zeros((0, 2)), 0.01, model, **ALONE)
        assert empty.params.shape == (0, 4) and empty.labels.shape == (0,)

import numpy as np
import pytest
import torch

from evseg_torch.errors import ModelError
from evseg_torch.motion import (
    Affine4,
    FailedEstimation,
    MotionEstimate,
    Rotation3D,
    Translation,
    make_motion_model,
)

SENSOR = (180, 240)
TRUE_PARAMS = {
    "translation": np.array([350.0, -120.0]),
    "affine4": np.array([300.0, -150.0, 2.5, -1.5]),
    "rotation3d": np.array([0.8, -1.2, 2.0]),
}


def _model(name):
    return make_motion_model(name, SENSOR)


def _correspondences(name, n=40, noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    model = _model(name)
    src = rng.uniform([0, 0], [SENSOR[1], SENSOR[0]], size=(n, 2))
    dt = rng.uniform(0.01, 0.03, size=n)
    dst = model.predict(src, dt, TRUE_PARAMS[name]) + rng.normal(scale=noise, size=(n, 2))
    return model, src, dst, dt


class TestWarp:
    def test_translation_exact(self):
        xy = np.array([[10.0, 20.0], [0.0, 0.0]])
        warped = Translation(SENSOR).warp(xy, np.array([0.01, -0.02]), np.array([100.0, -50.0]))
        np.testing.assert_allclose(warped, [[9.0, 20.5], [2.0, -1.0]])

    def test_affine4_scale_and_rotation_about_centre(self):
        model = Affine4((101, 101))
        centre = np.array([[50.0, 50.0]])
        np.testing.assert_allclose(model.warp(centre, np.array([0.1]), np.array([0, 0, 3.0, 2.0])), centre)
        # Pure rotation rate r moves (60, 50) with velocity (0, 10 r).
        np.testing.assert_allclose(
            model.velocity(np.array([[60.0, 50.0]]), np.array([0, 0, 0, 2.0])), [[0, 20]]
        )

    def test_rotation3d_matches_exact_rotation_to_first_order(self):
        model = Rotation3D(SENSOR, focal=(200.0, 200.0))
        omega, dt = TRUE_PARAMS["rotation3d"], 1e-4
        xy = np.array([[30.0, 40.0], [200.0, 150.0]])
        (fx, fy), (cx, cy) = model.focal, model.principal_point
        bearing = np.column_stack([(xy[:, 0] - cx) / fx, (xy[:, 1] - cy) / fy, np.ones(2)])
        moved = bearing - dt * np.cross(omega, bearing)  # a static point seen by a camera turning by omega
        exact = np.column_stack([fx * moved[:, 0] / moved[:, 2] + cx, fy * moved[:, 1] / moved[:, 2] + cy])
        np.testing.assert_allclose(model.predict(xy, dt, omega), exact, atol=1e-4)

    @pytest.mark.parametrize("name", sorted(TRUE_PARAMS))
    def test_batched_models_match_single(self, name):
        model = _model(name)
        xy = np.random.default_rng(1).uniform(0, 150, (7, 2))
        dt = np.linspace(-0.01, 0.02, 7)
        params = np.stack([TRUE_PARAMS[name], 0.5 * TRUE_PARAMS[name]])
        batched = model.warp(xy, dt, params)
        assert batched.shape == (2, 7, 2)
        np.testing.assert_allclose(batched[1], model.warp(xy, dt, params[1]))

    @pytest.mark.parametrize("name", sorted(TRUE_PARAMS))
    def test_torch_matches_numpy(self, name, device, dtype):
        model = _model(name)
        xy = np.random.default_rng(2).uniform(0, 150, (9, 2))
        dt = np.linspace(0.0, 0.03, 9)
        expected = model.warp(xy, dt, TRUE_PARAMS[name][None])
        got = model.warp(
            torch.tensor(xy, device=device, dtype=dtype),
            torch.tensor(dt, device=device, dtype=dtype),
            torch.tensor(TRUE_PARAMS[name][None], device=device, dtype=dtype),
        )
        np.testing.assert_allclose(got.cpu().double().numpy(), expected, rtol=1e-5, atol=1e-3)

    @pytest.mark.parametrize("name", sorted(TRUE_PARAMS))
    def test_gradcheck(self, name):
        model = _model(name)
        gen = torch.Generator().manual_seed(0)
        xy = (torch.rand(12, 2, generator=gen, dtype=torch.float64) * 100).requires_grad_()
        dt = (torch.rand(12, generator=gen, dtype=torch.float64) * 0.03).requires_grad_()
        params = torch.tensor(np.stack([TRUE_PARAMS[name]] * 2), dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(model.warp, (xy, dt, params), fast_mode=True)


class TestEstimation:
    @pytest.mark.parametrize("name", sorted(TRUE_PARAMS))
    def test_minimal_solver_exact(self, name):
        model, src, dst, dt = _correspondences(name, n=_model(name).min_samples)
        estimate = model.from_estimate(src, dst, dt)
        assert isinstance(estimate, MotionEstimate) and estimate
        np.testing.assert_allclose(estimate.params, TRUE_PARAMS[name], rtol=1e-8)
        assert np.all(estimate.residuals(src, dst, dt) < 1e-9)

    @pytest.mark.parametrize("name", sorted(TRUE_PARAMS))
    def test_least_squares_with_noise(self, name):
        model, src, dst, dt = _correspondences(name, n=400, noise=0.3)
        estimate = model.from_estimate(src, dst, dt)
        # The fit must predict the displacement over the image to within a fraction of the noise.
        grid = np.stack(np.meshgrid(np.linspace(0, 239, 5), np.linspace(0, 179, 5)), -1).reshape(-1, 2)
        error = np.linalg.norm(model.predict(grid, 0.03, estimate.params - TRUE_PARAMS[name]) - grid, axis=1)
        assert error.max() < 0.15

    def test_weights_ignore_outliers(self):
        model, src, dst, dt = _correspondences("affine4", n=50)
        dst = dst.copy()
        dst[:10] += 30.0
        weights = np.r_[np.zeros(10), np.ones(40)]
        np.testing.assert_allclose(model.from_estimate(src, dst, dt, weights).params, TRUE_PARAMS["affine4"])

    def test_degenerate_and_too_few(self):
        model = Affine4(SENSOR)
        same = np.array([[10.0, 10.0], [10.0, 10.0]])
        failed = model.from_estimate(same, same + 1, 0.01)
        assert isinstance(failed, FailedEstimation) and not failed and "degenerate" in failed.message
        assert not model.from_estimate(same[:1], same[:1], 0.01)

    def test_batch_flags_degenerate_samples_only(self):
        model, src, dst, dt = _correspondences("affine4", n=4)
        src_b = np.stack([src[:2], np.repeat(src[:1], 2, axis=0)])
        dst_b = np.stack([dst[:2], np.repeat(dst[:1], 2, axis=0)])
        params, valid = model.estimate_batch(src_b, dst_b, np.stack([dt[:2], dt[:2]]))
        assert valid.tolist() == [True, False]
        np.testing.assert_allclose(params[0], TRUE_PARAMS["affine4"])

    @pytest.mark.parametrize(
        ("args", "message"),
        [
            ((np.zeros((3, 2)), np.zeros((2, 2)), 0.1), "src and dst"),
            ((np.zeros((3, 2)), np.zeros((3, 2)), 0.0), "non-zero"),
            ((np.full((3, 2), np.nan), np.zeros((3, 2)), 0.1), "NaN"),
        ],
    )
    def test_exception(self, args, message):
        with pytest.raises(ModelError, match=message):
            Translation(SENSOR).from_estimate(*args)


class TestConventions:
    def test_affine4_paper_round_trip_and_values(self):
        model = Affine4(SENSOR)
        params = TRUE_PARAMS["affine4"]
        paper = model.to_paper(params)
        np.testing.assert_allclose(model.from_paper(paper), params)
        # Both conventions must describe the same velocity field (paper: origin at the top-left pixel).
        m, m_s, m_theta = paper[:2], paper[2], paper[3]
        rot = np.array([[np.cos(m_theta), -np.sin(m_theta)], [np.sin(m_theta), np.cos(m_theta)]])
        xy = np.array([[0.0, 0.0], [100.0, 30.0]])
        paper_velocity = m + xy @ ((1 + m_s) * rot - np.eye(2)).T
        np.testing.assert_allclose(model.velocity(xy, params), paper_velocity)

    def test_displacement_scale_conditions_parameters(self):
        for name in TRUE_PARAMS:
            scale = _model(name).displacement_scale(0.03)
            assert scale.shape == (_model(name).n_params,) and np.all(scale > 0)

    def test_intrinsics_and_errors(self):
        k = np.array([[200.0, 0, 120], [0, 210.0, 90], [0, 0, 1]])
        model = Rotation3D.from_intrinsics(SENSOR, k)
        assert model.focal == (200.0, 210.0) and model.principal_point == (120.0, 90.0)
        with pytest.raises(ModelError, match="unknown motion model"):
            make_motion_model("homography", SENSOR)
        with pytest.raises(ModelError, match="positive"):
            Translation((0, 10))
        with pytest.raises(ModelError, match="focal"):
            Rotation3D(SENSOR, focal=(0.0, 1.0))


class TestInstances:
    @pytest.mark.parametrize("name", sorted(TRUE_PARAMS))
    def test_plausible_and_check(self, name):
        model = _model(name)
        # The true parameters move pixels at hundreds of px/s; scaled by 1e12 they are no image motion.
        stack = np.stack([TRUE_PARAMS[name], 1e12 * TRUE_PARAMS[name], np.full(model.n_params, 1e307)])
        np.testing.assert_array_equal(model.plausible(stack), [True, False, False])
        checked = model.check_instances(stack[:1])
        np.testing.assert_array_equal(checked, stack[:1])
        assert checked is not stack
        with pytest.raises(ModelError, match="row 1 moves pixels faster"):
            model.check_instances(stack)

    def test_check_rejects_malformed(self):
        model = _model("affine4")
        for bad in (np.zeros(4), np.zeros((2, 3)), np.full((1, 4), np.nan)):
            with pytest.raises(ModelError, match="initial_models must be finite"):
                model.check_instances(bad)

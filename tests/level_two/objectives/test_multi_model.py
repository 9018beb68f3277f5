import math

import numpy as np
import pytest
import torch

from evseg_torch.errors import ConfigError, ShapeError
from evseg_torch.events import EventBatch, batch_windows, to_torch
from evseg_torch.level_two import MultiModelContrastLoss, contrast_loss, multi_model_contrast_loss
from evseg_torch.motion import Affine4, Translation
from evseg_torch.synthetic import make_scene

SCENE_SIZE = (90, 120)
DURATION = 0.03


def _window(n=20, seed=0, dtype=torch.float64, device="cpu"):
    generator = torch.Generator().manual_seed(seed)
    xy = 2.0 + torch.rand(n, 2, generator=generator, dtype=dtype) * 3.0
    t = torch.rand(n, generator=generator, dtype=dtype) * 0.05
    return EventBatch(xy, t, torch.ones(n, dtype=dtype)).to(device)


def _assignments(*shape, seed=0, dtype=torch.float64):
    generator = torch.Generator().manual_seed(seed)
    return torch.randn(*shape, generator=generator, dtype=dtype).softmax(dim=-1)


def _params(*shape, seed=0, dtype=torch.float64):
    generator = torch.Generator().manual_seed(seed)
    return torch.randn(*shape, generator=generator, dtype=dtype)


@pytest.fixture(scope="module")
def scene():
    """A background and one object; noise events are assigned half to each cluster."""
    scene = make_scene(SCENE_SIZE, DURATION, n_objects=1, rng=0)
    events = to_torch(scene.events, dtype=torch.float64)
    labels = torch.as_tensor(scene.labels)
    assignments = torch.nn.functional.one_hot(labels.clamp_min(0), 2).double()
    assignments[labels < 0] = 0.5
    truth = torch.as_tensor(np.stack([motion.params for motion in scene.motions]))
    return scene.motions[0].model, events, assignments, truth


class TestMultiModelContrastLoss:
    def test_smoke(self, device, dtype):
        events = _window(dtype=dtype, device=device)
        assignments = _assignments(20, 3, dtype=dtype).to(device)
        params = torch.zeros(3, 4, dtype=dtype, device=device)
        loss = multi_model_contrast_loss(Affine4((8, 8)), events, assignments, params)
        assert loss.shape == () and loss.dtype == dtype and loss.device.type == device.type
        assert torch.isfinite(loss) and loss < 0

    def test_cardinality(self):
        model, windows = Affine4((8, 8)), [_window(20, seed=0), _window(13, seed=1)]
        batch, assignments, params = batch_windows(windows), _assignments(2, 20, 3), _params(2, 3, 4)
        per_window = multi_model_contrast_loss(model, batch, assignments, params, reduction="none")
        assert per_window.shape == (2,)
        for reduction, reduce in (("mean", torch.mean), ("sum", torch.sum)):
            loss = multi_model_contrast_loss(model, batch, assignments, params, reduction=reduction)
            assert loss.shape == ()
            torch.testing.assert_close(loss, reduce(per_window))
        for reduction in ("none", "mean", "sum"):
            single = multi_model_contrast_loss(
                model, windows[0], assignments[0], params[0], reduction=reduction
            )
            assert single.shape == ()

    def test_is_the_sum_of_contrast_losses(self):
        # Built on contrast_loss: each cluster's term is contrast_loss with the assignments as weights.
        model, events = Affine4((8, 8)), _window()
        assignments, params = _assignments(20, 3), _params(3, 4)
        loss = multi_model_contrast_loss(model, events, assignments, params, objective="normalized_variance")
        expected = contrast_loss(model, events, params, assignments.T, objective="normalized_variance").sum()
        torch.testing.assert_close(loss, expected)

    def test_balance_term(self):
        model, events, params = Affine4((8, 8)), _window(), _params(3, 4)

        def gap(assignments):
            terms = [
                multi_model_contrast_loss(model, events, assignments, params, balance_weight=weight)
                for weight in (0.0, 0.5)
            ]
            return terms[1] - terms[0]

        uniform = torch.full((20, 3), 1 / 3, dtype=torch.float64)
        one_cluster = torch.nn.functional.one_hot(torch.zeros(20, dtype=torch.int64), 3).double()
        one_empty = torch.nn.functional.one_hot(torch.arange(20) % 2, 3).double()
        torch.testing.assert_close(gap(uniform), torch.tensor(0.0, dtype=torch.float64))
        torch.testing.assert_close(gap(one_cluster), torch.tensor(0.5 * math.log(3), dtype=torch.float64))
        torch.testing.assert_close(gap(one_empty), torch.tensor(0.5 * math.log(3 / 2), dtype=torch.float64))

    @pytest.mark.parametrize("model", [Translation((8, 8)), Affine4((8, 8))], ids=lambda m: m.name)
    def test_gradcheck(self, model):
        events = _window()
        assignments = _assignments(20, 2).requires_grad_()
        params = torch.tensor(np.linspace(0.5, 2.0, model.n_params))[None].repeat(2, 1).requires_grad_()
        assert torch.autograd.gradcheck(
            lambda a, p: multi_model_contrast_loss(model, events, a, p, balance_weight=0.3),
            (assignments, params),
            fast_mode=True,
        )
        batch = batch_windows([_window(12, seed=1), _window(7, seed=2)])
        assignments = _assignments(2, 12, 2, seed=3).requires_grad_()
        params = _params(2, 2, model.n_params, seed=4).requires_grad_()
        assert torch.autograd.gradcheck(
            lambda a, p: multi_model_contrast_loss(
                model, batch, a, p, objective="normalized_variance", balance_weight=0.3, reduction="none"
            ),
            (assignments, params),
            fast_mode=True,
        )

    def test_module(self):
        model, batch = Affine4((8, 8)), batch_windows([_window(20, seed=0), _window(13, seed=1)])
        assignments, params = _assignments(2, 20, 3), _params(2, 3, 4)
        options = {"objective": "normalized_variance", "balance_weight": 0.2, "reduction": "none"}
        module = MultiModelContrastLoss(model, **options)
        torch.testing.assert_close(
            module(batch, assignments, params),
            multi_model_contrast_loss(model, batch, assignments, params, **options),
        )
        window = _window()
        torch.testing.assert_close(
            MultiModelContrastLoss(model)(window, assignments[0], params[0]),
            multi_model_contrast_loss(model, window, assignments[0], params[0]),
        )
        assert "balance_weight=0.2" in repr(module) and "reduction='none'" in repr(module)

    @pytest.mark.parametrize("objective", ["variance", "normalized_variance"])
    def test_padded_batch_equals_windows(self, objective):
        model = Affine4((8, 8))
        windows = [_window(20, seed=0), _window(9, seed=1), _window(14, seed=2)]
        assignments = [_assignments(len(w), 3, seed=k) for k, w in enumerate(windows)]
        params = _params(3, 3, 4)
        padded = torch.zeros(3, 20, 3, dtype=torch.float64)
        for row, own in enumerate(assignments):
            padded[row, : len(own)] = own
        options = {"objective": objective, "balance_weight": 0.1}
        batched = multi_model_contrast_loss(
            model, batch_windows(windows), padded, params, reduction="none", **options
        )
        for row, window in enumerate(windows):
            alone = multi_model_contrast_loss(model, window, assignments[row], params[row], **options)
            torch.testing.assert_close(batched[row], alone)

    def test_padding_does_not_change_the_loss(self):
        model, window = Affine4((8, 8)), _window(10)
        assignments, params = _assignments(10, 2), _params(1, 2, 4)
        alone = multi_model_contrast_loss(model, window, assignments, params[0], balance_weight=0.1)
        batch = batch_windows([window])
        padded = EventBatch(
            torch.nn.functional.pad(batch.xy, (0, 0, 0, 6)),
            torch.nn.functional.pad(batch.t, (0, 6)),
            torch.nn.functional.pad(batch.p, (0, 6)),
            batch.lengths,
        )
        # Padding may hold anything, even NaN; it neither counts nor fails the sum-to-one check.
        garbage = torch.cat([assignments, torch.full((6, 2), float("nan"), dtype=torch.float64)])[None]
        garbage.requires_grad_()
        loss = multi_model_contrast_loss(model, padded, garbage, params, balance_weight=0.1)
        torch.testing.assert_close(loss, alone)
        loss.backward()
        assert torch.all(garbage.grad[0, 10:] == 0) and torch.isfinite(garbage.grad).all()

    def test_true_assignments_and_motions_are_best(self, scene):
        model, events, assignments, truth = scene
        for objective in ("variance", "normalized_variance"):

            def loss(a, objective=objective):
                return multi_model_contrast_loss(model, events, a, truth, objective=objective)

            true = loss(assignments)
            assert true < loss(assignments.flip(1)), objective
            assert true < loss(torch.full_like(assignments, 0.5)), objective

    def test_adam_lowers_the_loss(self, scene):
        # Parameters conditioned in pixels of displacement over the window, as ContrastMaximization does.
        model, events, assignments, truth = scene
        scale = torch.as_tensor(model.displacement_scale(DURATION))
        generator = torch.Generator().manual_seed(0)
        start = truth * scale + 2.0 * torch.randn(truth.shape, generator=generator, dtype=torch.float64)
        conditioned = torch.nn.Parameter(start.clone())
        optimiser = torch.optim.Adam([conditioned], lr=0.2)
        losses = []
        for _ in range(15):
            optimiser.zero_grad()
            loss = multi_model_contrast_loss(model, events, assignments, conditioned / scale)
            loss.backward()
            optimiser.step()
            losses.append(loss.item())
        final = multi_model_contrast_loss(model, events, assignments, conditioned.detach() / scale).item()
        assert final < losses[0] - 0.1 * abs(losses[0]), losses
        assert (conditioned.detach() - truth * scale).norm() < (start - truth * scale).norm()

    def test_device(self, device):
        model, windows = Affine4((8, 8)), [_window(20, seed=0), _window(13, seed=1)]
        assignments, params = _assignments(2, 20, 3), _params(2, 3, 4)
        expected = multi_model_contrast_loss(
            model, batch_windows(windows), assignments, params, reduction="none"
        )
        on_device = multi_model_contrast_loss(
            model,
            batch_windows([w.to(device) for w in windows]),
            assignments.to(device),
            params.to(device),
            reduction="none",
        )
        assert on_device.device.type == device.type
        torch.testing.assert_close(on_device.cpu(), expected)

    def test_exception(self):
        model, window = Affine4((8, 8)), _window()
        batch = batch_windows([window, _window(13, seed=1)])
        assignments, params = _assignments(20, 3), _params(3, 4)
        with pytest.raises(ShapeError, match=r"assignments must be \(B, N_max, K\) = \(2, 20, 3\)"):
            multi_model_contrast_loss(model, batch, _assignments(3, 20, 3), _params(2, 3, 4))
        with pytest.raises(ShapeError, match=r"assignments must be \(B, N_max, K\)"):
            multi_model_contrast_loss(model, batch, _assignments(2, 20, 3), _params(3, 3, 4))
        with pytest.raises(ShapeError, match=r"\(B, N_max, K\) and params \(B, K, P\)"):
            multi_model_contrast_loss(model, batch, assignments, params)
        with pytest.raises(ShapeError, match=r"assignments must be \(N, K\) and params \(K, P\)"):
            multi_model_contrast_loss(model, window, assignments[None], params)
        with pytest.raises(ShapeError, match=r"assignments must be \(B, N_max, K\)"):
            multi_model_contrast_loss(model, window, _assignments(19, 3), params)
        with pytest.raises(ShapeError, match=r"params must be \(\.\.\., K, 4\) with K >= 1 for the affine4"):
            multi_model_contrast_loss(model, window, assignments, _params(3, 2))
        with pytest.raises(ShapeError, match="sum to 1"):
            multi_model_contrast_loss(model, window, 2 * assignments, params)
        with pytest.raises(ShapeError, match=">= 0"):
            negative = assignments.clone()
            negative[0] = torch.tensor([1.5, -0.5, 0.0])
            multi_model_contrast_loss(model, window, negative, params)
        with pytest.raises(ShapeError, match="must be an EventBatch"):
            multi_model_contrast_loss(model, window.xy, assignments, params)
        with pytest.raises(ConfigError, match="reduction"):
            multi_model_contrast_loss(model, window, assignments, params, reduction="max")
        with pytest.raises(ConfigError, match="balance_weight"):
            MultiModelContrastLoss(model, balance_weight=-1.0)
        with pytest.raises(ConfigError, match="unknown contrast objective"):
            MultiModelContrastLoss(model, objective="sharpness")
        with pytest.raises(ConfigError, match="collapse_weight"):
            multi_model_contrast_loss(model, window, assignments, params, collapse_weight=-1.0)

import numpy as np
import pytest
import torch

from evseg_torch.errors import ConfigError, ShapeError
from evseg_torch.events import EventBatch
from evseg_torch.level_two.image.blur import gaussian_blur
from evseg_torch.level_two.image.splat import ImageOfWarpedEvents, extent_mask, splat_events, warped_iwe
from evseg_torch.level_two.image.warp import warp_events
from evseg_torch.motion import Affine4, Rotation3D, Translation

MODELS = [Translation((8, 8)), Affine4((8, 8)), Rotation3D((8, 8))]


def _inside(n, size=(8, 8), seed=0, dtype=torch.float64, device="cpu"):
    generator = torch.Generator().manual_seed(seed)
    xy = 2.0 + torch.rand(n, 2, generator=generator, dtype=torch.float64) * (torch.tensor(size[::-1]) - 5.0)
    return xy.to(device=device, dtype=dtype)


class TestSplatEvents:
    def test_smoke(self, device, dtype):
        image = splat_events(_inside(20, dtype=dtype, device=device), (8, 8))
        assert image.dtype == dtype and image.device.type == device.type
        assert torch.all(image >= 0)

    @pytest.mark.parametrize(
        ("xy_shape", "w_shape", "out"),
        [
            ((20, 2), None, (8, 8)),
            ((3, 20, 2), (3, 20), (3, 8, 8)),
            ((20, 2), (4, 20), (4, 8, 8)),
            ((2, 3, 20, 2), (20,), (2, 3, 8, 8)),
            ((3, 0, 2), None, (3, 8, 8)),
        ],
    )
    def test_cardinality(self, xy_shape, w_shape, out):
        xy = torch.rand(xy_shape) * 7
        weights = None if w_shape is None else torch.rand(w_shape)
        assert splat_events(xy, (8, 8), weights).shape == out

    def test_exception(self):
        with pytest.raises(ShapeError, match=r"xy must have shape \(\.\.\., N, 2\)"):
            splat_events(torch.rand(20, 3), (8, 8))
        with pytest.raises(ShapeError, match="weights must be"):
            splat_events(torch.rand(20, 2), (8, 8), torch.rand(19))
        with pytest.raises(ShapeError, match="do not broadcast"):
            splat_events(torch.rand(3, 20, 2), (8, 8), torch.rand(2, 20))
        with pytest.raises(ShapeError, match=r"polarity .* do not broadcast"):
            splat_events(torch.rand(3, 20, 2), (8, 8), polarity=torch.ones(2, 20))
        with pytest.raises(ShapeError, match="sensor_size"):
            splat_events(torch.rand(20, 2), (8, 0))
        with pytest.raises(ShapeError, match="floating-point"):
            splat_events(torch.ones(20, 2, dtype=torch.int64), (8, 8))
        with pytest.raises(ConfigError, match="sigma"):
            splat_events(torch.rand(20, 2), (8, 8), sigma=-1.0)

    def test_bilinear_votes(self):
        xy = torch.tensor([[3.0, 4.0], [2.5, 2.25], [7.0, 7.5]])
        image = splat_events(xy, (8, 8), sigma=0)
        expected = torch.zeros(8, 8)
        expected[4, 3] = 1.0
        expected[2, 2] = expected[2, 3] = 0.375
        expected[3, 2] = expected[3, 3] = 0.125
        expected[7, 7] = 0.5  # the other half falls below the image and is dropped
        torch.testing.assert_close(image, expected)

    def test_mass_equals_weights_inside(self, device, dtype):
        xy = torch.rand(200, 2, dtype=dtype, device=device) * 10 + 5  # 5 px from a 20x20 border
        weights = torch.rand(200, dtype=dtype, device=device)
        image = splat_events(xy, (20, 20), weights, sigma=1.0)
        torch.testing.assert_close(image.sum(), weights.sum())

    def test_far_outside_events_vanish(self):
        xy = torch.tensor([[-50.0, 3.0], [3.0, 1e6], [-1.5, -1.5], [8.5, 3.0]])
        assert splat_events(xy, (8, 8)).abs().max() == 0

    def test_batch_equals_separate_calls(self):
        xy, weights = torch.rand(2, 3, 30, 2) * 7, torch.rand(2, 3, 30)
        batched = splat_events(xy, (8, 8), weights)
        for b in range(2):
            for k in range(3):
                torch.testing.assert_close(batched[b, k], splat_events(xy[b, k], (8, 8), weights[b, k]))

    def test_blur_matches_kornia(self):
        kornia = pytest.importorskip("kornia")
        image = torch.rand(2, 12, 15, dtype=torch.float64)
        expected = kornia.filters.gaussian_blur2d(image[:, None], (7, 7), (1.0, 1.0), border_type="constant")
        torch.testing.assert_close(gaussian_blur(image, 1.0), expected[:, 0])

    def test_gradcheck(self):
        xy = _inside(20).requires_grad_()
        weights = torch.rand(20, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(
            lambda a, b: splat_events(a, (8, 8), b), (xy, weights), fast_mode=True
        )
        image = torch.rand(2, 6, 7, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradgradcheck(lambda a: gaussian_blur(a, 1.0), (image,))

    @pytest.mark.parametrize("model", MODELS, ids=lambda m: m.name)
    def test_gradcheck_through_warp(self, model):
        xy, t = _inside(20), torch.rand(20, dtype=torch.float64) * 0.05
        params = torch.tensor(np.linspace(0.5, 2.0, model.n_params))[None].repeat(2, 1).requires_grad_()
        events = EventBatch(xy, t, torch.ones(20, dtype=torch.float64))
        assert torch.autograd.gradcheck(lambda p: warped_iwe(model, events, p), (params,), fast_mode=True)

    def test_polarity_splits_the_image(self):
        xy, weights = torch.rand(3, 30, 2) * 7, torch.rand(3, 30)
        polarity = torch.tensor([1.0, -1.0, 0.0]).repeat(10)  # 0 (no sign) counts as negative
        split = splat_events(xy, (8, 8), weights, polarity=polarity)
        assert split.shape == (3, 2, 8, 8)
        torch.testing.assert_close(split.sum(1), splat_events(xy, (8, 8), weights))
        positive = polarity > 0
        torch.testing.assert_close(split[:, 0], splat_events(xy[:, positive], (8, 8), weights[:, positive]))
        torch.testing.assert_close(split[:, 1], splat_events(xy[:, ~positive], (8, 8), weights[:, ~positive]))
        # Shared events, K weightings and one polarity per event.
        assert splat_events(xy[0], (8, 8), weights, polarity=polarity).shape == (3, 2, 8, 8)
        with pytest.raises(ShapeError, match="polarity"):
            splat_events(xy, (8, 8), polarity=polarity[:5])
        with pytest.raises(ShapeError, match="polarity"):
            splat_events(xy, (8, 8), polarity=[1.0] * 30)

    def test_gradcheck_with_polarity(self):
        xy = _inside(20).requires_grad_()
        polarity = torch.tensor([1.0, -1.0], dtype=torch.float64).repeat(10)
        assert torch.autograd.gradcheck(
            lambda a: splat_events(a, (8, 8), polarity=polarity), (xy,), fast_mode=True
        )

    def test_module(self):
        xy, weights = torch.rand(3, 30, 2) * 7, torch.rand(3, 30)
        module = ImageOfWarpedEvents((8, 8), sigma=0.7)
        torch.testing.assert_close(module(xy, weights), splat_events(xy, (8, 8), weights, sigma=0.7))
        polarity = torch.randn(30).sign()
        torch.testing.assert_close(
            module(xy, weights, polarity), splat_events(xy, (8, 8), weights, sigma=0.7, polarity=polarity)
        )
        assert "sigma=0.7" in repr(module)


class TestExtent:
    @pytest.mark.parametrize("polarity", [False, True])
    def test_each_image_equals_its_size_alone(self, device, polarity):
        # Images of three sizes in one canvas: inside its extent each is the image of its size, bit for
        # bit on the CPU (zeros beyond the extent blur as the border's zero padding does).
        sizes = [(8, 8), (6, 7), (5, 9)]
        xy = torch.stack([_inside(40, size=(8, 9), seed=seed) for seed in range(3)]).to(device)
        weights = torch.rand(3, 40, dtype=torch.float64, generator=torch.Generator().manual_seed(1)).to(
            device
        )
        sign = torch.randn(3, 40, dtype=torch.float64, generator=torch.Generator().manual_seed(2)).to(device)
        extent = torch.tensor(sizes, device=device)
        canvas = splat_events(xy, (8, 9), weights, polarity=sign if polarity else None, extent=extent)
        for k, (height, width) in enumerate(sizes):
            alone = splat_events(xy[k], (height, width), weights[k], polarity=sign[k] if polarity else None)
            torch.testing.assert_close(canvas[k][..., :height, :width], alone, atol=1e-12, rtol=0)
            if device.type == "cpu":
                assert torch.equal(canvas[k][..., :height, :width], alone)

    def test_gradcheck(self):
        xy = _inside(12, size=(6, 7)).requires_grad_()
        extent = torch.tensor([[4, 5], [6, 7]])
        assert torch.autograd.gradcheck(
            lambda p: splat_events(p.expand(2, -1, -1), (6, 7), extent=extent), (xy,), fast_mode=True
        )

    def test_mask(self):
        mask = extent_mask(torch.tensor([[2, 3], [1, 1]]), (3, 4))
        assert mask.shape == (2, 3, 4)
        assert mask.sum((1, 2)).tolist() == [6, 1] and mask[0, :2, :3].all() and mask[1, 0, 0]


class TestWarpEvents:
    @pytest.mark.parametrize("model", MODELS, ids=lambda m: m.name)
    def test_matches_model_warp(self, model):
        xy, t = torch.rand(30, 2, dtype=torch.float64) * 7, torch.rand(30, dtype=torch.float64) * 0.03
        params = torch.rand(4, model.n_params, dtype=torch.float64) * 10
        torch.testing.assert_close(warp_events(model, xy, t, params), model.warp(xy, t, params))
        paired = warp_events(model, xy.expand(4, 30, 2), t.expand(4, 30), params)
        torch.testing.assert_close(paired, model.warp(xy, t, params))

    def test_exception(self):
        with pytest.raises(ShapeError, match="params must be"):
            warp_events(Affine4((8, 8)), torch.rand(5, 2), torch.rand(5), torch.rand(3, 2))
        with pytest.raises(ShapeError, match="t must have shape"):
            warp_events(Affine4((8, 8)), torch.rand(5, 2), torch.rand(4), torch.rand(3, 4))


class TestWarpedIwe:
    def test_cardinality(self):
        events = EventBatch(torch.rand(40, 2) * 7, torch.rand(40) * 0.01, torch.ones(40))
        model = Affine4((8, 8))
        assert warped_iwe(model, events, torch.zeros(3, 4)).shape == (3, 8, 8)
        assert warped_iwe(model, events, torch.zeros(4), sensor_size=(6, 9)).shape == (6, 9)

    def test_zero_motion_is_unwarped_image(self):
        events = EventBatch(torch.rand(40, 2) * 7, torch.rand(40) * 0.01, torch.ones(40))
        image = warped_iwe(Rotation3D((8, 8)), events, torch.zeros(2, 3))
        torch.testing.assert_close(image[1], splat_events(events.xy, (8, 8)))

import pytest
import torch

from evseg_torch.errors import ShapeError
from evseg_torch.level_two.image.splat import extent_mask, splat_events
from evseg_torch.level_two.image.variance import iwe_variance
from evseg_torch.level_two.objectives.contrast import image_variance

SIZE = (12, 17)


def _inputs(dtype=torch.float32, seed=0):
    generator = torch.Generator().manual_seed(seed)
    # Some positions beyond the canvas, whose taps land in the dropped border.
    xy = (
        torch.rand(3, 40, 2, generator=generator, dtype=dtype) * torch.tensor([20.0, 15.0], dtype=dtype) - 1.5
    )
    weights = torch.rand(3, 40, generator=generator, dtype=dtype)
    return xy, weights


def _composed(xy, weights, sigma, extent):
    images = splat_events(xy, SIZE, weights, sigma, extent=extent)
    mask = None if extent is None else extent_mask(extent, SIZE)
    return image_variance(images, mask=mask)


@pytest.mark.parametrize("sigma", [0.0, 1.0])
@pytest.mark.parametrize("cropped", [False, True])
def test_equals_splat_then_variance_with_gradients(sigma, cropped):
    xy, weights = _inputs()
    extent = torch.tensor([[12, 17], [7, 9], [10, 4]]) if cropped else None
    fused_xy, fused_w = xy.clone().requires_grad_(), weights.clone().requires_grad_()
    plain_xy, plain_w = xy.clone().requires_grad_(), weights.clone().requires_grad_()
    fused = iwe_variance(fused_xy, fused_w, SIZE, sigma, extent)
    plain = _composed(plain_xy, plain_w, sigma, extent)
    torch.testing.assert_close(fused, plain, rtol=1e-5, atol=1e-7)
    upstream = torch.tensor([1.0, -2.0, 0.5])
    (fused * upstream).sum().backward()
    (plain * upstream).sum().backward()
    torch.testing.assert_close(fused_xy.grad, plain_xy.grad, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(fused_w.grad, plain_w.grad, rtol=1e-4, atol=1e-6)


def test_gradients_against_finite_differences():
    xy, weights = _inputs(torch.float64, seed=1)
    extent = torch.tensor([[12, 17], [7, 9], [10, 4]])
    # Bilinear voting is piecewise linear: positions kept away from pixel boundaries by the checks' steps.
    xy = xy.floor() + 0.3 + 0.4 * (xy - xy.floor())
    torch.autograd.gradcheck(
        lambda p, w: iwe_variance(p, w, SIZE, 1.0, extent), (xy.requires_grad_(), weights.requires_grad_())
    )


def test_rows_are_independent():
    xy, weights = _inputs()
    extent = torch.tensor([[12, 17], [7, 9], [10, 4]])
    together = iwe_variance(xy, weights, SIZE, 1.0, extent)
    for row in range(3):
        alone = iwe_variance(xy[row : row + 1], weights[row : row + 1], SIZE, 1.0, extent[row : row + 1])
        assert torch.equal(together[row : row + 1], alone)


def test_shapes_are_checked():
    xy, weights = _inputs()
    with pytest.raises(ShapeError, match=r"xy \(R, n, 2\) and weights \(R, n\)"):
        iwe_variance(xy, weights[:, :5], SIZE, 1.0)

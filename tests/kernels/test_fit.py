"""The compiled fit evaluation (backend ``numba``) against the tensor code it stands in for."""

import numpy as np
import pytest
import torch

from evseg_torch.backend import using_backend
from evseg_torch.events import EventBatch
from evseg_torch.level_two.image.splat import extent_mask
from evseg_torch.level_two.image.warp import LinearWarp
from evseg_torch.level_two.objectives.contrast import MIN_AREA, warped_contrast_loss_and_grad
from evseg_torch.level_two.solver.cmax import ContrastMaximization
from evseg_torch.motion import Affine4, Rotation3D, Translation
from tests.helpers.level_two import DURATION, displacement_error, edge_scene

fit_kernel = pytest.importorskip("evseg_torch.kernels.fit")

CANVAS = (40, 56)


def _clusters(model, seed=0, n=400):
    """Four float32 clusters in one canvas: the third padded with zero-weight events, the fourth reaching
    beyond its extent and the canvas; their extents and per-cluster seeds."""
    generator = torch.Generator().manual_seed(seed)
    xy = torch.rand(4, n, 2, generator=generator) * torch.tensor([50.0, 34.0]) + 2.0
    xy[3, : n // 4] *= 1.6  # beyond the canvas
    t = torch.rand(4, n, generator=generator) * DURATION
    weights = torch.rand(4, n, generator=generator)
    weights[2, n // 2 :] = 0
    params = torch.randn(4, model.n_params, generator=generator)
    params = (
        params * torch.as_tensor(model.displacement_scale(DURATION), dtype=torch.float32).reciprocal() * 3
    )
    extent = np.array([[40, 56], [30, 44], [40, 56], [24, 36]], dtype=np.int64)
    seed_values = torch.tensor([-1.0, -0.5, -2.0, -1.5])
    return (
        LinearWarp.build(model, EventBatch(xy, t, torch.ones_like(t))),
        weights,
        params,
        extent,
        seed_values,
    )


@pytest.mark.parametrize("model", [Translation(CANVAS), Affine4(CANVAS), Rotation3D(CANVAS)])
@pytest.mark.parametrize("collapse_weight", [0.0, 0.375])
@pytest.mark.parametrize("sigma", [0.0, 1.0, 1.7])
def test_kernel_equals_tensor_code(model, collapse_weight, sigma):
    warp, weights, params, extent, seed = _clusters(model)
    if collapse_weight == 0:
        warp = warp._replace(maps=warp.maps[..., :2].contiguous())
    loss, grad = fit_kernel.loss_and_grad(
        warp, params, weights, extent, sigma, collapse_weight, MIN_AREA, seed
    )
    mask = extent_mask(torch.as_tensor(extent), CANVAS)
    expected_loss, expected_grad = warped_contrast_loss_and_grad(
        warp, params, weights, CANVAS, "variance", sigma, collapse_weight, None, mask, -1 / seed
    )
    torch.testing.assert_close(loss, expected_loss, rtol=1e-5, atol=0)
    # Float32 rounding, summed in other orders: relative to each cluster's largest component.
    scale = expected_grad.abs().amax(dim=1, keepdim=True)
    torch.testing.assert_close(grad / scale, expected_grad / scale, rtol=0, atol=1e-4)


def test_kernel_clusters_are_independent_bit_for_bit():
    # A cluster's result does not depend on the others in the call or on zero-weight padding: batched
    # equals solo exactly.
    warp, weights, params, extent, seed = _clusters(Affine4(CANVAS))
    args = (1.0, 0.375, MIN_AREA)
    loss, grad = fit_kernel.loss_and_grad(warp, params, weights, extent, *args, seed)
    own = LinearWarp(warp.xy[2:3, :200], warp.maps[:, 2:3, :200].contiguous())
    alone_loss, alone_grad = fit_kernel.loss_and_grad(
        own, params[2:3], weights[2:3, :200], extent[2:3], *args, seed[2:3]
    )
    assert torch.equal(loss[2:3], alone_loss) and torch.equal(grad[2:3], alone_grad)


def test_losses_alone_equal_the_losses_with_gradients():
    # Discovery scores its regions by the losses alone: the backward pass is skipped, the losses are the same.
    warp, weights, params, extent, seed = _clusters(Affine4(CANVAS))
    args = (warp, params, weights, extent, 1.0, 0.375, MIN_AREA, seed)
    loss, grad = fit_kernel.loss_and_grad(*args)
    alone, none = fit_kernel.loss_and_grad(*args, gradient=False)
    assert torch.equal(alone, loss) and none is None and grad is not None


def test_corner_and_clamp_follow_python_semantics():
    # The compiled steps' tap and clamp helpers (written with np.floor and comparisons for speed) give
    # math.floor's taps and min(max(...))'s values, signed zeros and ties included.
    import math

    from evseg_torch.kernels.common import bilinear_corner
    from evseg_torch.kernels.data_term import _clamp

    values = np.float32([-0.0, 0.0, -1.0, -0.5, -1e-8, 1e-8, 0.99999994, 3.0, 238.99998, 239.0, 1e6])
    for x in values:
        col, row, fx, fy = bilinear_corner(x, -x)
        assert (col, row) == (math.floor(x), math.floor(-x))
        expected = np.float32(x) - np.float32(math.floor(x)), np.float32(-x) - np.float32(math.floor(-x))
        assert np.float32([fx, fy]).tobytes() == np.float32(expected).tobytes()
        for low, high in ((np.float32(0.0), np.float32(1.0)), (np.float32(-0.0), np.float32(238.0))):
            assert np.float32(_clamp(x, low, high)).tobytes() == np.float32(min(max(x, low), high)).tobytes()


@pytest.mark.parametrize("name", ["translation", "affine4", "rotation3d"])
def test_fits_agree_across_backends(name):
    # A float32 fit (the pipeline's dtype, the only one the compiled loop serves) from 30% off lands on
    # the motion through either backend, and both land together.
    model, truth, events, start = edge_scene(name, dtype=torch.float32)
    start = torch.tensor(start, dtype=torch.float32)[None]
    fitted = {}
    for backend in ("numba", "torch"):
        with using_backend(backend):
            fitted[backend] = ContrastMaximization(model, max_iter=30)(events, start)[0]
    for params in fitted.values():
        assert displacement_error(model, params, truth, events, DURATION) < 0.04
    assert displacement_error(model, fitted["numba"], fitted["torch"].numpy(), events, DURATION) < 0.005


def test_only_float32_fits_on_the_cpu_take_the_kernel():
    cmax = ContrastMaximization(Translation(CANVAS))
    with using_backend("numba"):
        assert cmax._kernel_for(torch.zeros(1, 2)) is fit_kernel.loss_and_grad
        assert cmax._kernel_for(torch.zeros(1, 2, dtype=torch.float64)) is None
    with using_backend("torch"):
        assert cmax._kernel_for(torch.zeros(1, 2)) is None

r"""The variance of blurred images of warped events, with one hand-written backward pass.

Contrast maximisation evaluates ``var(blur(splat(x')))`` and its gradient hundreds of times per window,
mostly on small crops, where autograd's bookkeeping of the forty-odd nodes of that composition costs
more than its arithmetic (1.1 of 1.7 ms for 1400 events in a 116 x 53 crop). :func:`iwe_variance`
computes the same as :func:`~evseg_torch.level_two.iwe.splat_events` followed by
:func:`~evseg_torch.level_two.contrast.image_variance`, from the same helpers (tested against them,
values and gradients), as one autograd node. Its backward pass is three steps: the gradient image
``2 (B - mean) / |Ω|`` of the blurred image ``B``; the same blur of it (the blur is symmetric, so its
own adjoint); and a read of that image at each event's four bilinear taps, which gives the gradient of
each event's position and weight.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from evseg_torch.errors import ShapeError
from evseg_torch.level_two.iwe import bilinear_taps, extent_mask, gaussian_blur
from evseg_torch.level_two.linear_warp import sum_ignoring_padding


def iwe_variance(
    xy: Tensor, weights: Tensor, size: tuple[int, int], sigma: float, extent: Tensor | None = None
) -> Tensor:
    """Variance of each cluster's blurred image of weighted (warped) events.

    Args:
        xy: event positions :math:`(R, n, 2)`, ``x`` the column.
        weights: event weights :math:`(R, n)`.
        size: the canvas ``(H, W)``.
        sigma: Gaussian blur in pixels (0: none).
        extent: optional int64 ``(height, width)`` of each image in the canvas, :math:`(R, 2)`
            (see :func:`~evseg_torch.level_two.iwe.splat_events`); the variance is then over those
            pixels, by sums that the canvas beyond them does not change.

    Returns:
        :math:`(R,)`, differentiable in ``xy`` and ``weights``.
    """
    if xy.ndim != 3 or xy.shape[-1] != 2 or weights.shape != xy.shape[:2]:
        raise ShapeError(
            f"iwe_variance needs xy (R, n, 2) and weights (R, n), got {tuple(xy.shape)} and "
            f"{tuple(weights.shape)}"
        )
    return _IWEVariance.apply(xy, weights, size, float(sigma), extent)


class _IWEVariance(torch.autograd.Function):
    @staticmethod
    def forward(ctx, xy: Tensor, weights: Tensor, size: tuple[int, int], sigma: float, extent):
        height, width = size
        n_rows = xy.shape[0]
        padded = (height + 4) * (width + 4)
        corner, taps = bilinear_taps(xy, weights, height, width)
        index = corner + torch.arange(n_rows, device=xy.device)[:, None] * padded
        image = xy.new_zeros(n_rows * padded)
        for step, tap in taps:
            image.index_add_(0, (index + step).flatten(), tap.flatten())
        image = image.view(n_rows, height + 4, width + 4)[:, 2 : height + 2, 2 : width + 2]
        inside = None if extent is None else extent_mask(extent, size)
        if inside is not None:
            image = image * inside
        blurred = gaussian_blur(image, sigma)
        if inside is None:
            count = torch.full((n_rows,), float(height * width), dtype=xy.dtype, device=xy.device)
            flat = blurred.flatten(-2)  # as image_variance, to round alike
            deviation = (flat - flat.mean(dim=-1, keepdim=True)).view_as(blurred)
            variance = deviation.flatten(-2).square().mean(dim=-1)
        else:
            count = inside.sum(dim=(-2, -1)).to(xy.dtype)
            mean = sum_ignoring_padding(sum_ignoring_padding(torch.where(inside, blurred, 0))) / count
            deviation = torch.where(inside, blurred - mean[:, None, None], 0)
            variance = sum_ignoring_padding(sum_ignoring_padding(deviation.square())) / count
        fraction = xy - xy.detach().floor()
        ctx.save_for_backward(index, fraction, weights, deviation, count)
        ctx.inside, ctx.sigma, ctx.size = inside, sigma, size
        return variance

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        index, fraction, weights, deviation, count = ctx.saved_tensors
        height, width = ctx.size
        # The deviations sum to zero over each image, so the mean carries no gradient.
        grad_image = gaussian_blur(deviation * (2 * grad / count)[:, None, None], ctx.sigma)
        if ctx.inside is not None:
            grad_image = grad_image * ctx.inside
        padded = grad_image.new_zeros(grad_image.shape[0], height + 4, width + 4)
        padded[:, 2 : height + 2, 2 : width + 2] = grad_image
        flat = padded.flatten()
        stride = width + 4
        g00, g01 = flat[index], flat[index + 1]
        g10, g11 = flat[index + stride], flat[index + stride + 1]
        fx, fy = fraction.unbind(-1)
        top = torch.lerp(g00, g01, fx)  # the taps' gradient along the upper and lower rows
        bottom = torch.lerp(g10, g11, fx)
        grad_weights = torch.lerp(top, bottom, fy)
        grad_x = weights * torch.lerp(g01 - g00, g11 - g10, fy)
        grad_y = weights * (bottom - top)
        return torch.stack([grad_x, grad_y], dim=-1), grad_weights, None, None, None

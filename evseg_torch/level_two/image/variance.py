r"""The variance of blurred images of warped events, with one hand-written backward pass.

Contrast maximisation evaluates ``var(blur(splat(x')))`` and its gradient hundreds of times per window,
mostly on small crops, where autograd's bookkeeping of the forty-odd nodes of that composition costs
more than its arithmetic (1.1 of 1.7 ms for 1400 events in a 116 x 53 crop). :func:`iwe_variance`
computes the same as :func:`~evseg_torch.level_two.image.splat.splat_events` followed by
:func:`~evseg_torch.level_two.objectives.contrast.image_variance`, from the same helpers (tested against them,
values and gradients), as one autograd node. Its backward pass is three steps: the gradient image
``2 (B - mean) / |Ω|`` of the blurred image ``B``; the same blur of it (the blur is symmetric, so its
own adjoint); and a read of that image at each event's four bilinear taps, which gives the gradient of
each event's position and weight.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from evseg_torch.errors import ShapeError
from evseg_torch.level_two.image.blur import gaussian_blur
from evseg_torch.level_two.image.splat import bilinear_taps, extent_mask, read_flat, scatter_taps
from evseg_torch.level_two.image.warp import sum_ignoring_padding

__all__ = ["centred_variance", "iwe_variance", "iwe_variance_and_pullback"]


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
            (see :func:`~evseg_torch.level_two.image.splat.splat_events`); the variance is then over those
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


def centred_variance(image: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor | int]:
    r"""Variance of each image over its pixels, with the deviations from its mean and the pixel count.

    The one computation behind :func:`~evseg_torch.level_two.objectives.contrast.image_variance` and
    :func:`iwe_variance`. With ``mask`` :math:`(..., H, W)`, broadcastable (the pixels of each image in
    a larger canvas), the sums are ones that the zeros beyond an image's pixels do not change, so an
    image has the same variance and gradient, bit for bit, alone and in any larger canvas; the mean is
    then detached (the deviations sum to zero, so no gradient flows through it, and autograd's rounded
    sum of them would depend on the canvas).

    Args:
        image: :math:`(..., H, W)`.
        mask: optional bool :math:`(..., H, W)`; ``None`` for all pixels.

    Returns:
        ``(variance, deviation, count)``: :math:`(...)`, :math:`(..., H, W)` (0 outside the mask), and
        the pixels counted, :math:`(...)` or ``H * W``.
    """
    if mask is None:
        flat = image.flatten(-2)
        # Written out: torch.var's forward and backward take twice as long on CPU.
        deviation = flat - flat.mean(dim=-1, keepdim=True)
        return deviation.square().mean(dim=-1), deviation.view_as(image), flat.shape[-1]
    count = mask.sum(dim=(-2, -1))
    mean = sum_ignoring_padding(sum_ignoring_padding(torch.where(mask, image, 0))) / count
    deviation = torch.where(mask, image - mean.detach()[..., None, None], 0)
    return sum_ignoring_padding(sum_ignoring_padding(deviation.square())) / count, deviation, count


def iwe_variance_and_pullback(
    xy: Tensor, weights: Tensor, size: tuple[int, int], sigma: float, mask: Tensor | None = None
) -> tuple[Tensor, Callable[[Tensor], tuple[Tensor, Tensor]]]:
    """:func:`iwe_variance` without autograd: the variances and the map of their gradient back to the
    events, for callers that chain the gradient by hand (the fits' evaluations,
    :func:`~evseg_torch.level_two.objectives.contrast.warped_contrast_loss_and_grad`).

    Args:
        xy, weights, size, sigma: as in :func:`iwe_variance`.
        mask: optional bool :math:`(R, H, W)`, each image's pixels of the canvas: the
            :func:`~evseg_torch.level_two.image.splat.extent_mask` of :func:`iwe_variance`'s ``extent``.

    Returns:
        ``(variance, pullback)``: the variances :math:`(R,)`, and a function of the gradient
        :math:`(R,)` of a loss with respect to them that returns the loss's gradients with respect to
        ``xy`` :math:`(R, n, 2)` and ``weights`` :math:`(R, n)`.
    """
    corner, taps = bilinear_taps(xy, weights, *size)
    image, index = scatter_taps(corner, taps, weights.shape, *size)
    if mask is not None:
        image = image * mask
    variance, deviation, count = centred_variance(gaussian_blur(image, sigma), mask)
    fraction = xy - xy.floor()

    def pullback(grad: Tensor) -> tuple[Tensor, Tensor]:
        width = size[1]
        pixels = count if isinstance(count, int) else count[:, None, None]
        # The deviations sum to zero over each image, so the mean carries no gradient.
        grad_image = gaussian_blur(deviation * (2 * grad[:, None, None] / pixels), sigma)
        if mask is not None:
            grad_image = grad_image * mask
        # The layout of scatter_taps' images: 2 pixels of padding each side.
        flat = torch.nn.functional.pad(grad_image, (2, 2, 2, 2)).flatten()
        stride = width + 4
        g00, g01 = read_flat(flat, index), read_flat(flat, index + 1)
        g10, g11 = read_flat(flat, index + stride), read_flat(flat, index + stride + 1)
        fx, fy = fraction.unbind(-1)
        top = torch.lerp(g00, g01, fx)  # the taps' gradient along the upper and lower rows
        bottom = torch.lerp(g10, g11, fx)
        grad_weights = torch.lerp(top, bottom, fy)
        grad_x = weights * torch.lerp(g01 - g00, g11 - g10, fy)
        grad_y = weights * (bottom - top)
        return torch.stack([grad_x, grad_y], dim=-1), grad_weights

    return variance, pullback


class _IWEVariance(torch.autograd.Function):
    @staticmethod
    def forward(ctx, xy: Tensor, weights: Tensor, size: tuple[int, int], sigma: float, extent):
        mask = None if extent is None else extent_mask(extent, size)
        variance, ctx.pullback = iwe_variance_and_pullback(xy.detach(), weights.detach(), size, sigma, mask)
        return variance

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        grad_xy, grad_weights = ctx.pullback(grad)
        return grad_xy, grad_weights, None, None, None

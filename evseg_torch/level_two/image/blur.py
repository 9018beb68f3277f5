"""The separable Gaussian blur of images of warped events, and its taps.

EMSGC blurs its images of warped events with a Gaussian of width ``sigma`` (1 px) and zero padding.
:func:`gaussian_taps` defines the kernel once: the tensor code here and the compiled kernels
(:mod:`evseg_torch.kernels`) blur with the same taps, so their images agree bit for bit. The blur is a
symmetric linear map, so its backward pass is the same blur (:class:`_SymmetricBlur`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from evseg_torch.level_two.checks import check_blur

__all__ = ["BLUR_TRUNCATE", "gaussian_blur", "gaussian_taps"]

BLUR_TRUNCATE = 3.0
"""The blur kernel reaches ``ceil(BLUR_TRUNCATE * sigma)`` pixels each side."""


def gaussian_taps(sigma: float, truncate: float = BLUR_TRUNCATE) -> tuple[float, ...]:
    """The taps of :func:`gaussian_blur`: ``exp(-d^2 / (2 sigma^2))`` for ``|d| <= ceil(truncate * sigma)``,
    normalised to sum 1; one tap of 1 for ``sigma`` 0. The tensor code and the compiled kernels
    (:mod:`evseg_torch.kernels`) blur with these taps.

    Examples:
        >>> [round(tap, 3) for tap in gaussian_taps(0.5)]
        [0.0, 0.106, 0.787, 0.106, 0.0]
    """
    if sigma == 0:
        return (1.0,)
    radius = math.ceil(truncate * sigma)
    taps = [math.exp(-0.5 * (d / sigma) ** 2) for d in range(-radius, radius + 1)]
    total = math.fsum(taps)
    return tuple(tap / total for tap in taps)


def gaussian_blur(image: Tensor, sigma: float, truncate: float = BLUR_TRUNCATE) -> Tensor:
    r"""Separable Gaussian blur of the last two dimensions with zero padding.

    The kernel is ``exp(-d^2 / (2 sigma^2))`` for ``|d| <= ceil(truncate * sigma)``, normalised to
    sum 1 (as OpenCV's ``GaussianBlur`` and kornia's ``gaussian_blur2d``).

    Args:
        image: :math:`(..., H, W)`.
        sigma: standard deviation in pixels; 0 returns ``image`` itself.
        truncate: kernel radius in units of ``sigma``.

    Returns:
        :math:`(..., H, W)`.

    Examples:
        >>> gaussian_blur(torch.rand(2, 8, 8), 1.0).shape
        torch.Size([2, 8, 8])
    """
    check_blur(sigma, truncate)
    if sigma == 0:
        return image
    taps = gaussian_taps(sigma, truncate)
    if torch.is_grad_enabled() and image.requires_grad:
        return _SymmetricBlur.apply(image, taps)
    # Without a gradient to keep, the sums alone: the fits' evaluations blur twice each, mostly small
    # crops, where an autograd.Function's call cost a tenth of the blur.
    return _shifted_sums(image, taps)


class _SymmetricBlur(torch.autograd.Function):
    """Separable blur with a symmetric kernel and zero padding: a symmetric linear map, so its backward
    pass is the same blur. Autograd through the shifted sums would instead copy every shifted gradient
    into a padded buffer, which made the backward pass 5x slower than the forward."""

    @staticmethod
    def forward(ctx, image: Tensor, taps: tuple[float, ...]) -> Tensor:
        ctx.taps = taps
        return _shifted_sums(image, taps)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None]:
        return _SymmetricBlur.apply(grad, ctx.taps), None


def _shifted_sums(image: Tensor, taps: tuple[float, ...]) -> Tensor:
    # Sums of shifted copies: on CPU, conv1d/conv2d with one channel (and kornia's gaussian_blur2d, which
    # uses them) are slower, and their backward passes about 10x slower. The copies are views of one
    # padded image, all taken by one unfold (the same sums as one narrow per tap, in fewer calls).
    radius = len(taps) // 2
    for dim in (-1, -2):
        size = image.shape[dim]
        padded = nn.functional.pad(image, (radius, radius) if dim == -1 else (0, 0, radius, radius))
        shifted = padded.unfold(dim, size, 1)  # the shifts' dimension next to last, then the window
        shifted = shifted.unbind(-2) if dim == -1 else shifted.transpose(-1, -2).unbind(-3)
        blurred = taps[0] * shifted[0]
        for view, tap in zip(shifted[1:], taps[1:], strict=True):
            # In place: allocating a new image per tap made the blur about twice as slow.
            blurred.add_(view, alpha=tap)
        image = blurred
    return image

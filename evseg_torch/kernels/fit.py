r"""The fits' evaluation as one compiled loop per cluster on the CPU (Numba).

:func:`~evseg_torch.level_two.objectives.contrast.warped_contrast_loss_and_grad` evaluates a cluster's
contrast loss and its gradient in a few dozen tensor operations; on the small crops of discovery and
the refits (a few hundred to a few thousand events, 50 x 30 to 240 x 180 pixels) their calls, not their
arithmetic, take the time. :func:`loss_and_grad` computes the
same in one compiled pass per cluster: the warp and the event-collapse votes, the bilinear splat, the
separable Gaussian blur with zero padding, the variance, and the gradient back through the same steps
(the blur is symmetric, so its own adjoint). Each cluster's image is only its extent, so a cluster's
result does not depend on the others in a call (batched equals solo, bit for bit). The warped positions
and the blur equal the tensor code's bit for bit (fused multiply-adds where torch's kernels use them);
sums over pixels and events run in float64 over fixed lanes; the rest (the votes' ``pow``, the order of
the splat's additions) differs by rounding: losses within about 2e-7, gradients within about 3e-5 of
their largest component (tested).

Numba is an optional dependency (``pip install 'evseg-torch[fast]'``); this module is imported only
when :mod:`evseg_torch.backend` chooses it.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit
from torch import Tensor

from evseg_torch.kernels.common import ONE, ZERO, bilinear_corner, blur, blur_taps
from evseg_torch.level_two.image.warp import LinearWarp

_LANES = 8


def loss_and_grad(
    warp: LinearWarp,
    params: Tensor,
    weights: Tensor,
    extent: np.ndarray,
    sigma: float,
    collapse_weight: float,
    min_area: float,
    seed: Tensor,
    gradient: bool = True,
) -> tuple[Tensor, Tensor | None]:
    """``seed`` times each cluster's image variance, and its gradient in the parameters.

    Args:
        warp: the clusters' warps, events :math:`(R, n)`, float32 on the CPU.
        params: :math:`(R, P)`.
        weights: :math:`(R, n)`.
        extent: int64 ``(height, width)`` of each cluster's image, :math:`(R, 2)`; positions are
            relative to its top-left pixel.
        sigma: Gaussian blur in pixels (a kernel of ``ceil(3 sigma)`` taps each side, as
            :func:`~evseg_torch.level_two.image.blur.gaussian_blur`).
        collapse_weight: exponent γ of the event-collapse votes ``max(area, min_area) ** γ``; 0: none.
        min_area: the area element's floor.
        seed: :math:`(R,)`, the derivative of the loss in the variance.
        gradient: ``False`` for the losses alone (the same values; the backward pass is skipped).

    Returns:
        The losses :math:`(R,)` and their gradients :math:`(R, P)` (``None`` without ``gradient``).
    """
    rows, n_params = params.shape
    loss = np.empty(rows, np.float32)
    grad = np.empty((rows, n_params), np.float32)
    _loss_and_grad(
        warp.xy.numpy(),
        warp.maps.numpy(),
        params.contiguous().numpy(),
        weights.contiguous().numpy(),
        extent,
        blur_taps(sigma),
        np.float32(collapse_weight),
        np.float32(min_area),
        seed.contiguous().numpy(),
        loss,
        grad,
        gradient,
    )
    return torch.from_numpy(loss), torch.from_numpy(grad) if gradient else None


@njit(cache=True)
def _loss_and_grad(xy, maps, params, weights, extent, taps, gamma, min_area, seed, loss, grad, gradient):
    n_params, rows, n_events, n_channels = maps.shape
    moved = np.empty((n_events, n_channels), np.float32)
    grad_moved = np.empty((n_events, n_channels), np.float32)
    votes = np.empty(n_events, np.float32)
    for r in range(rows):
        height, width = extent[r, 0], extent[r, 1]
        image = np.zeros((height, width), np.float32)
        scratch = np.empty((height, width), np.float32)
        blurred = np.empty((height, width), np.float32)
        _move(maps, params, r, moved)
        for i in range(n_events):
            vote = weights[r, i]
            if gamma > 0:
                vote = max(_area(moved, i), min_area) ** gamma * vote
            votes[i] = vote
            _splat(image, xy[r, i, 0] - moved[i, 0], xy[r, i, 1] - moved[i, 1], vote)
        blur(image, scratch, blurred, taps)
        # The variance over the extent; ``blurred`` becomes the deviations from the mean.
        count = height * width
        flat = blurred.ravel()
        mean = np.float32(_sum(flat, flat, False) / count)
        flat -= mean
        square = _sum(flat, flat, True)
        loss[r] = seed[r] * np.float32(square / count)
        if not gradient:
            continue
        # d loss / d image = seed 2 (B - mean) / count, blurred back (the mean carries no gradient).
        flat *= np.float32(2.0) * seed[r] / np.float32(count)
        blur(blurred, scratch, image, taps)
        for i in range(n_events):
            x, y = xy[r, i, 0] - moved[i, 0], xy[r, i, 1] - moved[i, 1]
            _pull_back(image, x, y, votes[i], gamma, min_area, moved, grad_moved, i)
        for p in range(n_params):
            grad[r, p] = np.float32(_sum(maps[p, r].ravel(), grad_moved.ravel(), True))


@njit(cache=True, fastmath={"contract"})
def _move(maps, params, r, moved):
    """:meth:`LinearWarp.moved` of cluster ``r``'s events, ``moved`` :math:`(n, C)`; one contiguous
    pass per parameter, by fused multiply-adds as torch's ``addcmul``: the same positions bit for bit, so
    the bilinear votes' kinks at whole pixels fall alike."""
    n_params, _, n_events, n_channels = maps.shape
    first = params[r, 0]
    for i in range(n_events):
        for c in range(n_channels):
            moved[i, c] = maps[0, r, i, c] * first
    for p in range(1, n_params):
        value = params[r, p]
        for i in range(n_events):
            for c in range(n_channels):
                moved[i, c] += maps[p, r, i, c] * value


@njit(cache=True)
def _pull_back(image, x, y, vote, gamma, min_area, moved, grad_moved, i):
    """Row ``i`` of ``grad_moved`` :math:`(n, C)`, the gradient of event ``i``'s ``moved`` channels, from
    the gradient image at its warped position ``(x, y)``; 0 for an event whose taps all miss the image.
    (Scalars, not a view of the event's row: a view per event cost a quarter of this step.)"""
    for c in range(grad_moved.shape[1]):
        grad_moved[i, c] = 0.0
    height, width = image.shape
    if not _touches(x, y, height, width):
        return
    col, row, fx, fy = bilinear_corner(x, y)
    g00 = _pixel(image, row, col)
    g01 = _pixel(image, row, col + 1)
    g10 = _pixel(image, row + 1, col)
    g11 = _pixel(image, row + 1, col + 1)
    top = g00 + fx * (g01 - g00)
    bottom = g10 + fx * (g11 - g10)
    # The positions move against the displacement: x' = x - moved.
    grad_moved[i, 0] = -vote * ((g01 - g00) + fy * ((g11 - g10) - (g01 - g00)))
    grad_moved[i, 1] = -vote * (bottom - top)
    if gamma > 0:
        area = _area(moved, i)
        # d vote / d area = γ vote / area above the floor, 0 below it.
        change = (top + fy * (bottom - top)) * gamma * vote / area if area >= min_area else ZERO
        grad_moved[i, 2] = change * (moved[i, 5] - ONE)
        grad_moved[i, 3] = -change * moved[i, 4]
        grad_moved[i, 4] = -change * moved[i, 3]
        grad_moved[i, 5] = change * (moved[i, 2] - ONE)


@njit(cache=True)
def _sum(a, b, product):
    """``sum(a)``, or ``sum(a * b)`` with ``product``, in float64 over 8 fixed lanes added in order at the
    end (element ``k`` in lane ``k % 8``): vectorised, and zeros appended to ``a`` (padding events) change
    no lane."""
    lanes = np.zeros(_LANES, np.float64)
    length = len(a)
    full = length - length % _LANES
    for start in range(0, full, _LANES):
        for lane in range(_LANES):
            value = np.float64(a[start + lane])
            lanes[lane] += value * np.float64(b[start + lane]) if product else value
    for k in range(full, length):
        value = np.float64(a[k])
        lanes[k - full] += value * np.float64(b[k]) if product else value
    total = 0.0
    for lane in range(_LANES):
        total += lanes[lane]
    return total


@njit(cache=True)
def _area(moved, i):
    """:func:`~evseg_torch.level_two.image.warp.area_from` of event ``i``."""
    return (ONE - moved[i, 2]) * (ONE - moved[i, 5]) - moved[i, 3] * moved[i, 4]


@njit(cache=True)
def _touches(x, y, height, width):
    """Whether some bilinear tap of ``(x, y)`` is a pixel of the image (False for NaN)."""
    return x > -1.0 and x < width and y > -1.0 and y < height


@njit(cache=True)
def _pixel(image, row, col):
    if row < 0 or col < 0 or row >= image.shape[0] or col >= image.shape[1]:
        return ZERO
    return image[row, col]


@njit(cache=True)
def _splat(image, x, y, vote):
    """Add ``vote`` at ``(x, y)`` by bilinear voting; taps outside the image are dropped."""
    height, width = image.shape
    if not _touches(x, y, height, width):
        return
    col, row, fx, fy = bilinear_corner(x, y)
    top, bottom, left = (ONE - fy) * vote, fy * vote, ONE - fx
    if row >= 0:
        if col >= 0:
            image[row, col] += top * left
        if col + 1 < width:
            image[row, col + 1] += top * fx
    if row + 1 < height:
        if col >= 0:
            image[row + 1, col] += bottom * left
        if col + 1 < width:
            image[row + 1, col + 1] += bottom * fx

"""The data term's per-polarity images and reads as one compiled pass per model (Numba).

:func:`~evseg_torch.level_two.data_term.data_cost` with per-polarity images splats every event of a
window under every model of its pool into two images, blurs them and reads each event back from its
own sign's image: a dozen tensor passes over ``B * K * N`` positions and ``2 B K`` canvases.
:func:`polarity_values` does the same per model in one compiled loop whose arithmetic follows the
tensor code step by step: the bilinear votes added in the same order (every event's first tap, then
every event's second, ...), the blur of :func:`~evseg_torch.level_two.fit_kernel._blur` (the tensor
blur bit for bit), the reads' clamps and products in float32. Its values and ``inside`` flags equal the
tensor code's bit for bit (tested), so the choice changes no result; it serves where Numba (the
optional ``fast`` extra) is installed.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit
from torch import Tensor

from evseg_torch.level_two.fit_kernel import _ONE, _ZERO, _blur, _corner, blur_taps


def polarity_values(
    warped: Tensor, negative: Tensor, votes: Tensor, extent: np.ndarray, sigma: float
) -> tuple[Tensor, Tensor]:
    """Each event's value in its own sign's image under each model, and whether it lies inside the image.

    Args:
        warped: float32 CPU positions :math:`(B, K, N, 2)`, relative to the images' top-left pixel.
        negative: whether each event is negative (``p <= 0``), bool :math:`(B, N)`.
        votes: each event's vote, float32 :math:`(B, N)` (0 on the padding).
        extent: int64 ``(height, width)`` of each window's images, :math:`(B, 2)`, each at least 2 x 2.
        sigma: the images' Gaussian blur in pixels.

    Returns:
        ``(values, inside)``, float32 and bool :math:`(B, K, N)`, as
        :func:`~evseg_torch.level_two.data_term.sample_bilinear` reads the tensor code's images (0 outside).
    """
    n_windows, n_models, n_events = warped.shape[:3]
    values = np.empty((n_windows, n_models, n_events), np.float32)
    inside = np.empty((n_windows, n_models, n_events), np.bool_)
    _polarity_values(
        warped.contiguous().numpy(),
        negative.contiguous().numpy(),
        votes.contiguous().numpy(),
        np.ascontiguousarray(extent, dtype=np.int64),
        blur_taps(sigma),
        values,
        inside,
    )
    return torch.from_numpy(values), torch.from_numpy(inside)


@njit(cache=True)
def _polarity_values(warped, negative, votes, extent, taps, values, inside):
    n_windows, n_models, n_events = warped.shape[:3]
    # Each event's top-left tap and its four taps' weights, computed once for the four passes.
    corner = np.empty((n_events, 2), np.int64)
    weight = np.empty((4, n_events), np.float32)
    for b in range(n_windows):
        height, width = extent[b, 0], extent[b, 1]
        images = np.empty((2, height, width), np.float32)
        scratch = np.empty((height, width), np.float32)
        blurred = np.empty((2, height, width), np.float32)
        for k in range(n_models):
            images[:] = 0.0
            for i in range(n_events):
                x, y, vote = warped[b, k, i, 0], warped[b, k, i, 1], votes[b, i]
                corner[i, 0], corner[i, 1], fx, fy = _corner(x, y)
                top, bottom = (_ONE - fy) * vote, fy * vote
                weight[0, i], weight[1, i] = top * (_ONE - fx), top * fx
                weight[2, i], weight[3, i] = bottom * (_ONE - fx), bottom * fx
            # In the tensor code's order: every event's first tap, then every event's second, ...; taps
            # outside the image are dropped, padding events vote nothing.
            for tap in range(4):
                for i in range(n_events):
                    col, row = corner[i, 0] + tap % 2, corner[i, 1] + tap // 2
                    if votes[b, i] != 0 and col >= 0 and row >= 0 and col < width and row < height:
                        images[1 if negative[b, i] else 0, row, col] += weight[tap, i]
            for sign in range(2):
                _blur(images[sign], scratch, blurred[sign], taps)
            for i in range(n_events):
                inside[b, k, i], values[b, k, i] = _read(
                    blurred, 1 if negative[b, i] else 0, warped[b, k, i, 0], warped[b, k, i, 1]
                )


@njit(cache=True)
def _read(images, sign, x, y):
    """``(inside, value)`` of :func:`~evseg_torch.level_two.data_term.sample_bilinear` at ``(x, y)`` in
    ``images[sign]``."""
    height, width = images.shape[1], images.shape[2]
    if not (x >= 0 and x <= width - 1 and y >= 0 and y <= height - 1):
        return False, _ZERO
    # The clamps of ``sample_bilinear`` as comparisons: Numba's float ``min`` and ``max`` (the same
    # results, ties and signed zeros included) took most of this function's time.
    col = _clamp(np.floor(x), _ZERO, np.float32(width - 2))
    row = _clamp(np.floor(y), _ZERO, np.float32(height - 2))
    fx = _clamp(x - col, _ZERO, _ONE)
    fy = _clamp(y - row, _ZERO, _ONE)
    c, r = int(col), int(row)
    top = images[sign, r, c] * (_ONE - fx) + images[sign, r, c + 1] * fx
    bottom = images[sign, r + 1, c] * (_ONE - fx) + images[sign, r + 1, c + 1] * fx
    return True, top * (_ONE - fy) + bottom * fy


@njit(cache=True)
def _clamp(value, low, high):
    """``min(max(value, low), high)`` as Python (and Numba) evaluate it: the first argument on ties."""
    value = low if low > value else value
    return high if high < value else value

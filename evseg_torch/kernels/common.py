"""Compiled helpers shared by the kernels: constants, the bilinear corner, the blur, NaN-aware maximum.

Each helper follows the tensor code's arithmetic step by step (the kernels' module docstrings say how),
so a kernel built from them gives that code's values bit for bit where it claims to.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from evseg_torch.level_two.image.blur import gaussian_taps

ONE = np.float32(1.0)
ZERO = np.float32(0.0)


def blur_taps(sigma: float) -> np.ndarray:
    """The taps of :func:`~evseg_torch.level_two.image.blur.gaussian_blur` at ``sigma`` (one tap of 1 for
    ``sigma`` 0), float32."""
    return np.array(gaussian_taps(sigma), np.float32)


@njit(cache=True)
def bilinear_corner(x, y):
    """The top-left bilinear tap ``(col, row)`` of ``(x, y)`` and the position's fractions ``(fx, fy)``
    beyond it (float32, as the tensor code's ``xy - floor(xy)``). ``np.floor``, not ``math.floor``: the
    same taps, and a quarter of the time in Numba (a float32 ``math.floor`` goes through Python's int)."""
    col, row = int(np.floor(x)), int(np.floor(y))
    return col, row, x - np.float32(col), y - np.float32(row)


@njit(cache=True, fastmath={"contract"})
def blur(image, scratch, out, taps):
    """Separable blur of ``image`` into ``out`` with zero padding, rows first (``scratch``: same shape).
    Each pass runs along contiguous rows, which the compiler vectorises; fused multiply-adds, as torch's
    ``add_(alpha=)``, give :func:`~evseg_torch.level_two.image.blur.gaussian_blur`'s values bit for bit."""
    height, width = image.shape
    n_taps = len(taps)
    radius = n_taps // 2
    row = np.zeros(width + 2 * radius, np.float32)
    for y in range(height):
        for x in range(width):
            row[radius + x] = image[y, x]
            scratch[y, x] = 0.0
        for k in range(n_taps):
            tap = taps[k]
            for x in range(width):
                scratch[y, x] += tap * row[x + k]
    for y in range(height):
        for x in range(width):
            out[y, x] = 0.0
        for k in range(max(0, radius - y), min(n_taps, height - y + radius)):
            tap, source = taps[k], y + k - radius
            for x in range(width):
                out[y, x] += tap * scratch[source, x]


@njit(cache=True, error_model="numpy")
def maximum(a, b):
    """``np.maximum`` of two scalars: NaN if ``a`` is NaN."""
    return a if (a != a or a >= b) else b

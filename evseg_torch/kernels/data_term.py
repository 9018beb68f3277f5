"""The data term's per-polarity images and reads as one compiled pass per model (Numba).

:func:`~evseg_torch.level_two.energy.data_term.data_cost` with per-polarity images splats every event of a
window under every model of its pool into two images, blurs them and reads each event back from its
own sign's image: a dozen tensor passes over ``B * K * N`` positions and ``2 B K`` canvases.
:func:`polarity_values` does the same per model in one compiled loop whose arithmetic follows the
tensor code step by step: the bilinear votes added in the same order (every event's first tap, then
every event's second, ...), the blur of :func:`~evseg_torch.kernels.common.blur` (the tensor
blur bit for bit), the reads' clamps and products in float32. Its values and ``inside`` flags equal the
tensor code's bit for bit (tested), so the choice changes no result; it serves where Numba (the
optional ``fast`` extra) is installed. :func:`overshoots` and :func:`relative_costs` do the steps around it
(the images' margin; the "relative" normalisation with its floors' selections) as loops over the values,
with the same results as the tensor code (the quantiles are the same elements, the arithmetic the same
float32 operations).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit
from torch import Tensor

from evseg_torch.kernels.common import ONE, ZERO, bilinear_corner, blur, blur_taps, maximum

_MAX_COST = np.float32(255.0)
_TINY = np.finfo(np.float32).tiny


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
        :func:`~evseg_torch.level_two.energy.data_term.sample_bilinear` reads the tensor code's images
        (0 outside).
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
                corner[i, 0], corner[i, 1], fx, fy = bilinear_corner(x, y)
                top, bottom = (ONE - fy) * vote, fy * vote
                weight[0, i], weight[1, i] = top * (ONE - fx), top * fx
                weight[2, i], weight[3, i] = bottom * (ONE - fx), bottom * fx
            # In the tensor code's order: every event's first tap, then every event's second, ...; taps
            # outside the image are dropped, padding events vote nothing.
            for tap in range(4):
                for i in range(n_events):
                    col, row = corner[i, 0] + tap % 2, corner[i, 1] + tap // 2
                    if votes[b, i] != 0 and col >= 0 and row >= 0 and col < width and row < height:
                        images[np.int64(negative[b, i]), row, col] += weight[tap, i]
            for sign in range(2):
                blur(images[sign], scratch, blurred[sign], taps)
            for i in range(n_events):
                inside[b, k, i], values[b, k, i] = _read(
                    blurred, np.int64(negative[b, i]), warped[b, k, i, 0], warped[b, k, i, 1]
                )


@njit(cache=True)
def _read(images, sign, x, y):
    """``(inside, value)`` of :func:`~evseg_torch.level_two.energy.data_term.sample_bilinear` at ``(x, y)`` in
    ``images[sign]``."""
    height, width = images.shape[1], images.shape[2]
    if not (x >= 0 and x <= width - 1 and y >= 0 and y <= height - 1):
        return False, ZERO
    # The clamps of ``sample_bilinear`` as comparisons: Numba's float ``min`` and ``max`` (the same
    # results, ties and signed zeros included) took most of this function's time.
    col = _clamp(np.floor(x), ZERO, np.float32(width - 2))
    row = _clamp(np.floor(y), ZERO, np.float32(height - 2))
    fx = _clamp(x - col, ZERO, ONE)
    fy = _clamp(y - row, ZERO, ONE)
    c, r = int(col), int(row)
    top = images[sign, r, c] * (ONE - fx) + images[sign, r, c + 1] * fx
    bottom = images[sign, r + 1, c] * (ONE - fx) + images[sign, r + 1, c + 1] * fx
    return True, top * (ONE - fy) + bottom * fy


@njit(cache=True)
def _clamp(value, low, high):
    """``min(max(value, low), high)`` as Python (and Numba) evaluate it: the first argument on ties."""
    value = low if low > value else value
    return high if high < value else value


def overshoots(warped: Tensor, real: Tensor, height: int, width: int) -> np.ndarray:
    """Each window's largest overshoot of a real warped position beyond the sensor's pixel centres.

    Args:
        warped: float32 CPU positions :math:`(B, K, N, 2)`.
        real: which positions count, bool :math:`(B, 1, N)` or :math:`(B, K, N)`.
        height, width: the sensor's size.

    Returns:
        float32 :math:`(B,)`: ``-inf`` where no position counts, NaN where one is NaN (as
        :func:`~evseg_torch.level_two.energy.data_term._overshoots`).
    """
    n_windows, n_models = warped.shape[:2]
    overshoot = np.empty(n_windows, np.float32)
    flags = real.expand(n_windows, n_models, -1).contiguous().numpy()
    _overshoot(warped.contiguous().numpy(), flags, np.float32(width - 1), np.float32(height - 1), overshoot)
    return overshoot


@njit(cache=True)
def _overshoot(warped, real, last_col, last_row, out):
    n_windows, n_models, n_events = warped.shape[:3]
    for b in range(n_windows):
        largest = np.float32(-np.inf)
        for k in range(n_models):
            for i in range(n_events):
                if real[b, k, i]:
                    x, y = warped[b, k, i, 0], warped[b, k, i, 1]
                    # torch.maximum's NaN propagation, as the tensor code's overshoot.
                    beyond = maximum(maximum(-x, x - last_col), maximum(-y, y - last_row))
                    largest = maximum(largest, beyond)
        out[b] = largest


def relative_costs(
    values: Tensor,
    inside: Tensor,
    real: Tensor,
    floor_quantile: float | None,
    pool_floor_quantile: float | None,
) -> Tensor:
    """The "relative" costs of :func:`~evseg_torch.level_two.energy.data_term.data_cost` from its images'
    values.

    Two compiled passes (each event's best value and owner; the costs) around NumPy's selections of the
    floors, the tensor code's steps in its order.

    Args:
        values: each event's value under each model, float32 :math:`(B, K, N)` (from :func:`polarity_values`).
        inside: whether each value was read inside its image, bool :math:`(B, K, N)`.
        real: which events and models count, bool :math:`(B, 1, N)` or :math:`(B, K, N)`.
        floor_quantile, pool_floor_quantile: the floors' quantiles, or ``None`` for no such floor.

    Returns:
        float32 :math:`(B, N, K)`, the tensor code's costs bit for bit.
    """
    n_windows, n_models, n_events = values.shape
    masked = np.empty((n_windows, n_models, n_events), np.float32)
    counted = np.empty((n_windows, n_models, n_events), np.bool_)
    best = np.empty((n_windows, n_events), np.float32)
    owner = np.empty((n_windows, n_events), np.int64)
    seen = np.empty((n_windows, n_events), np.bool_)
    _best_values(
        values.contiguous().numpy(),
        inside.contiguous().numpy(),
        real.expand(n_windows, n_models, -1).contiguous().numpy(),
        masked,
        counted,
        best,
        owner,
        seen,
    )
    floor = np.full((n_windows, n_events), _TINY, np.float32)
    for b in range(n_windows):
        if pool_floor_quantile is not None:
            floor[b] = np.maximum(floor[b], _quantile(masked[b][counted[b]], pool_floor_quantile))
        if floor_quantile is not None:
            own = [_quantile(best[b][seen[b] & (owner[b] == k)], floor_quantile) for k in range(n_models)]
            floor[b] = np.maximum(floor[b], np.array(own, np.float32)[owner[b]])
    cost = np.empty((n_windows, n_events, n_models), np.float32)
    _costs(masked, counted, np.maximum(best, floor), cost)
    return torch.from_numpy(cost)


def _quantile(selected: np.ndarray, quantile: float) -> np.float32:
    """``data_term._quantile`` of one window's selected values: the element of rank ``round(n q)`` (at
    least 1), or the smallest normal float32 of none."""
    if not len(selected):
        return _TINY
    rank = max(round(len(selected) * quantile), 1)
    return np.partition(selected, rank - 1)[rank - 1]


@njit(cache=True)
def _best_values(values, inside, real, masked, counted, best, owner, seen):
    """Values outside their image or of padding as 0 (``values * inside``); each event's best value, the
    first model giving it (torch's ``max`` over the models) and whether some model's image holds it."""
    n_windows, n_models, n_events = values.shape
    for b in range(n_windows):
        for k in range(n_models):
            for i in range(n_events):
                counted[b, k, i] = inside[b, k, i] and real[b, k, i]
                masked[b, k, i] = values[b, k, i] * np.float32(counted[b, k, i])
        for i in range(n_events):
            best[b, i], owner[b, i], seen[b, i] = masked[b, 0, i], 0, counted[b, 0, i]
        for k in range(1, n_models):
            for i in range(n_events):
                if masked[b, k, i] > best[b, i]:
                    best[b, i], owner[b, i] = masked[b, k, i], k
                seen[b, i] = seen[b, i] or counted[b, k, i]


@njit(cache=True)
def _costs(masked, counted, peak, cost):
    """``255 (1 - min(value / peak, 1))`` inside, 255 elsewhere, as :math:`(B, N, K)`."""
    n_windows, n_models, n_events = masked.shape
    for b in range(n_windows):
        for i in range(n_events):
            for k in range(n_models):
                if counted[b, k, i]:
                    ratio = masked[b, k, i] / peak[b, i]
                    if ratio > ONE:
                        ratio = ONE
                    cost[b, i, k] = _MAX_COST * (ONE - ratio)
                else:
                    cost[b, i, k] = _MAX_COST

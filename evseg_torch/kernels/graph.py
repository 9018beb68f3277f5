"""The site graph's edge weights as one compiled pass over the pixel pairs (Numba).

:func:`~evseg_torch.level_two.energy.graph.site_graph` weighs an edge between two adjacent pixels ``p`` and
``q`` (one time slice) by the number of distinct event pairs that EMSGC's lookups join: every event's
latest event at or before it and earliest after it at the other pixel. The tensor-free NumPy code finds
them with one ``searchsorted`` per event and neighbour (about six per event) and then counts them;
that is about half the graph's time on a dense window. The count has a closed form: in the time order of
the two pixels' events, cut into runs of one pixel's events, every event but those of the last run has
an "earliest after" (the next run's first event), and every event but those of the first run has a
"latest before" (the previous run's last event), which the first event of its run shares with that event's
own "earliest after". So a pair with ``n`` events in ``m`` runs, the first of length ``a`` and the last
of length ``b``, has ``2 n - a - b - (m - 1)`` edges' worth of event pairs. :func:`pair_counts` walks each
pair's two time-ordered lists once: the same counts (integers, so the same graph bit for bit; tested).

Numba is an optional dependency (``pip install 'evseg-torch[fast]'``); without it the graph uses the
lookups.
"""

from __future__ import annotations

import numpy as np
from numba import njit


def pair_counts(pixel: np.ndarray, t: np.ndarray, pixel_pairs: np.ndarray) -> np.ndarray:
    """The number of event pairs that the lookups of :func:`~evseg_torch.level_two.energy.graph.event_graph`
    join across each pair of adjacent pixels.

    Args:
        pixel: each event's pixel index, int64 :math:`(N,)` in ``[0, P)``.
        t: the events' times :math:`(N,)`; ties are broken by event order.
        pixel_pairs: adjacent pixel indices, int64 :math:`(A, 2)`.

    Returns:
        float64 :math:`(A,)`.
    """
    by_time = np.argsort(t, kind="stable")
    counts = _pair_counts(pixel, by_time, int(pixel.max()) + 1, np.ascontiguousarray(pixel_pairs))
    return counts.astype(np.float64)


@njit(cache=True)
def _pair_counts(pixel, by_time, n_pixels, pixel_pairs):
    # Every pixel's events in time order (a counting sort by pixel of the events in time order): pixel
    # p's are time_rank[start[p]:start[p + 1]], as ranks in the window's time order.
    start = np.zeros(n_pixels + 1, np.int64)
    for event in range(len(pixel)):
        start[pixel[event] + 1] += 1
    for p in range(n_pixels):
        start[p + 1] += start[p]
    fill = start[:-1].copy()
    time_rank = np.empty(len(pixel), np.int64)
    for rank in range(len(by_time)):
        p = pixel[by_time[rank]]
        time_rank[fill[p]] = rank
        fill[p] += 1
    counts = np.empty(len(pixel_pairs), np.int64)
    for pair in range(len(pixel_pairs)):
        i, i_end = start[pixel_pairs[pair, 0]], start[pixel_pairs[pair, 0] + 1]
        j, j_end = start[pixel_pairs[pair, 1]], start[pixel_pairs[pair, 1] + 1]
        total = (i_end - i) + (j_end - j)
        runs, run, side, first_run = 0, 0, -1, 0
        while i < i_end or j < j_end:
            if j == j_end or (i < i_end and time_rank[i] < time_rank[j]):
                now, i = 0, i + 1
            else:
                now, j = 1, j + 1
            if now == side:
                run += 1
                continue
            if runs == 1:
                first_run = run
            runs, run, side = runs + 1, 1, now
        counts[pair] = 2 * total - first_run - run - (runs - 1)
    return counts

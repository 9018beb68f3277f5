"""Wall-clock time of level two's stages, per window."""

from __future__ import annotations

import time
from collections.abc import Sequence

from evseg_torch.level_two.descent.state import WindowState

__all__ = ["STAGES", "StageClock"]

STAGES = ("graph", "data_term", "labelling", "refit", "discovery", "images")
"""The stages of level two that :class:`StageClock` times."""


class StageClock:
    """Wall-clock milliseconds per stage and window; a stage run for several windows at once is shared
    evenly by them, so the windows' timings add up to the batch's."""

    def __init__(self, n_windows: int) -> None:
        self.timings = [dict.fromkeys(STAGES, 0.0) for _ in range(n_windows)]
        self._last = time.perf_counter()

    def lap(self, stage: str, windows: Sequence[WindowState]) -> None:
        now = time.perf_counter()
        share = 1e3 * (now - self._last) / len(windows)
        for window in windows:
            self.timings[window.index][stage] += share
        self._last = now

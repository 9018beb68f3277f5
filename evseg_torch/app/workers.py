"""Worker processes that segment the windows of a batch side by side, one CPU core each.

A stream's batch holds windows that do not depend on each other (each starts from the models of the
batch before), so its windows can be shared out among processes: :meth:`WindowPool.segment` is a
``segment_windows`` for :meth:`~evseg_torch.pipeline.CascadedSegmenter.stream`. Each worker holds its own
copy of the segmenter and runs :meth:`~evseg_torch.pipeline.CascadedSegmenter.segment_batch` on its share
with one thread (torch's and OpenCV's: :mod:`evseg_torch.app.threads`). Level two gives every window of a
batch the result it gets alone (bit for bit on one torch thread), so the results equal those of one
process on one thread, window by window.

Processes, not threads: PyMaxflow holds the GIL through every graph cut, and level one is mostly
Python. They start the platform's default way, as torch's DataLoader workers do: forked on Linux
(nothing to re-import), spawned on macOS and Windows, where the calling script needs the usual
``if __name__ == "__main__":`` guard. OpenCV's thread pool is wound down to one thread while the workers
fork (a worker that inherits its state without its threads would hang in its first
``cv2.setNumThreads``), then restored.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Sequence

import numpy as np

from evseg_torch.app.signals import worker_signals
from evseg_torch.app.threads import set_threads
from evseg_torch.errors import ConfigError
from evseg_torch.validation import check_integer

__all__ = ["WindowPool"]

_segmenter = None  # each worker's own copy, set once by _start


def _start(segmenter) -> None:
    global _segmenter
    worker_signals()
    set_threads(1)
    _segmenter = segmenter


def _segment(windows: list, initial_models, level_one) -> list:
    return _segmenter._segment(windows, initial_models, level_one)


class WindowPool:
    """A pool of ``workers`` processes, each with a copy of ``segmenter``; use as a context manager.

    Args:
        segmenter: a :class:`~evseg_torch.pipeline.CascadedSegmenter` (pickled once per worker).
        workers: number of processes, at least 1 (2 or more to share anything out).
        batch_size: the windows of the batches to come, if known; the workers share out the windows of
            one batch, so they must not outnumber them.

    Raises:
        ConfigError: ``workers`` is not a positive integer, or exceeds ``batch_size``.

    Examples:
        >>> from evseg_torch.pipeline import CascadedSegmenter
        >>> from evseg_torch.synthetic import make_scene
        >>> events = make_scene((90, 120), duration=0.06, n_objects=1, rng=0).events
        >>> segmenter = CascadedSegmenter((90, 120))
        >>> with WindowPool(segmenter, 2, batch_size=2) as pool:
        ...     results = segmenter.stream(events, window_ms=30, batch_size=2, segment_windows=pool.segment)
        ...     [result.window_index for result in results]
        [0, 1]
    """

    def __init__(self, segmenter, workers: int, batch_size: int | None = None) -> None:
        self.workers = check_integer(workers, "workers", at_least=1)
        if batch_size is not None and workers > batch_size:
            raise ConfigError(
                f"workers ({workers}) must not exceed batch_size ({batch_size}): the workers share out "
                "the windows of one batch"
            )
        # A worker forked while OpenCV's thread pool exists in this process would hang in its first
        # cv2.setNumThreads (the pool's state is copied without its threads): the pool is wound down to
        # this thread for the fork, then restored.
        import cv2

        threads = cv2.getNumThreads()
        cv2.setNumThreads(1)
        try:
            context = multiprocessing.get_context()
            self._pool = context.Pool(workers, initializer=_start, initargs=(segmenter,))
        finally:
            cv2.setNumThreads(threads)

    def segment(self, windows: Sequence, initial_models, level_one: Sequence[bool] | None = None) -> list:
        """Segment ``windows`` (each starting from ``initial_models``), shared out in consecutive parts.

        Args:
            windows: B windows, each in any form the segmenter accepts.
            initial_models: :math:`(M, P)` models every window starts from, or ``None``.
            level_one: whether level one runs in each window (``None``: as the config says).

        Returns:
            One :class:`~evseg_torch.pipeline.Segmentation` per window, in order.
        """
        parts = [part for part in np.array_split(np.arange(len(windows)), self.workers) if len(part)]
        tasks = [
            self._pool.apply_async(
                _segment,
                (
                    [windows[index] for index in part],
                    initial_models,
                    None if level_one is None else [level_one[index] for index in part],
                ),
            )
            for part in parts
        ]
        return [result for task in tasks for result in task.get()]

    def close(self) -> None:
        """Let the workers finish and end them."""
        self._pool.close()
        self._pool.join()

    def __enter__(self) -> WindowPool:
        return self

    def __exit__(self, kind, error, traceback) -> None:
        if kind is None:
            self.close()
        else:
            # Stopped or failed: end the workers at once rather than wait for their windows.
            self._pool.terminate()
            self._pool.join()

"""The CPU threads of one process: torch's intra-op pool and OpenCV's.

OpenCV runs its own loops (Lucas-Kanade's points, blurs, dilations) on a pool of its own, by default as
many threads as the machine has cores, and ``torch.set_num_threads`` does not reach it. A process meant
to use one core (each worker of ``--workers``, a Dask task) sets both; otherwise N such processes start N
times the machine's cores in OpenCV threads, and level one's tracking of a "one thread" process runs on
several. OpenCV's count does not change results (its loops are split over independent points and
pixels); torch's can (a reduction split over more threads rounds otherwise), which is one reason one
thread is the command line's default.
"""

from __future__ import annotations

from evseg_torch.validation import check_integer

__all__ = ["set_threads"]


def set_threads(threads: int) -> None:
    """Use ``threads`` CPU threads in this process, in torch and in OpenCV.

    Args:
        threads: at least 1.

    Raises:
        ConfigError: ``threads`` is not a positive integer.
    """
    threads = check_integer(threads, "threads", at_least=1)
    import cv2
    import torch

    torch.set_num_threads(int(threads))
    cv2.setNumThreads(int(threads))

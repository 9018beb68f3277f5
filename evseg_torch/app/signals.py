"""Stopping a run by a signal: SIGTERM and SIGINT in the main process, and in worker processes.

SIGTERM and SIGINT both raise :class:`Stopped` in the main process (:func:`stop_on_signals`); the flag
it also sets is checked after every window (:func:`raise_if_stopped`), so an interrupt that lands where
Python ignores exceptions (a finaliser) still stops the run at the next window. A worker process
(:func:`worker_signals`) leaves Ctrl-C to the parent and ends at once on SIGTERM.
"""

from __future__ import annotations

import signal
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["Stopped", "raise_if_stopped", "stop_on_signals", "stopped_by", "worker_signals"]


class Stopped(KeyboardInterrupt):
    """The run was asked to stop by a signal (SIGINT or SIGTERM); ``signum`` says which."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


_stop_requested: list[int] = []


@contextmanager
def stop_on_signals() -> Iterator[None]:
    """Within the block, SIGTERM and SIGINT raise :class:`Stopped` (main thread only)."""

    def stop(signum, frame):
        _stop_requested.append(signum)
        raise Stopped(signum)

    previous = {number: signal.signal(number, stop) for number in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
        _stop_requested.clear()


def stopped_by(err: BaseException) -> Stopped | None:
    """The :class:`Stopped` that ``err`` was raised from (its cause or context, at any depth), or ``None``."""
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, Stopped):
            return err
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return None


def raise_if_stopped() -> None:
    """Raise :class:`Stopped` if a signal asked the run to stop."""
    if _stop_requested:
        raise Stopped(_stop_requested[0])


def worker_signals() -> None:
    """In a worker process: the parent alone handles Ctrl-C, and SIGTERM ends the worker at once."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)

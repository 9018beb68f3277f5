"""Cutting a stream of canonical events into windows, by time or by event count, chunk by chunk.

:class:`TimeWindowIndex` and :class:`CountWindowIndex` find each window's ``[begin, end)`` event indices
while the stream passes; :func:`iter_windows` cuts the windows' events with them, holding only what the
next window needs; :func:`window_ranges_by_time` and :func:`window_ranges_by_count` give the ranges of
a whole array at once.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import NamedTuple

import numpy as np

from evseg_torch.errors import EventFormatError
from evseg_torch.events.format import EVENT_DTYPE


def window_ranges_by_time(
    t_us: np.ndarray, window_ms: float, stride_ms: float | None = None, start_us: int | None = None
) -> np.ndarray:
    """Index ranges of fixed-duration windows over sorted timestamps, as :class:`TimeWindowIndex` cuts them.

    Window ``i`` covers ``[start + i*stride, start + i*stride + window)``. Only windows that start
    at or before the last timestamp are returned, empty ones (gaps) included.

    Args:
        t_us: sorted timestamps in microseconds, :math:`(N,)`.
        window_ms: window length in milliseconds.
        stride_ms: step between window starts; defaults to ``window_ms`` (no overlap).
        start_us: start of the first window; defaults to the first timestamp.

    Returns:
        int64 array :math:`(M, 2)` of ``[begin, end)`` indices into ``t_us``.

    Raises:
        EventFormatError: a window or stride that is not positive, or timestamps that decrease.

    Examples:
        >>> window_ranges_by_time(np.array([0, 1000, 2500, 2600, 7000]), window_ms=2, stride_ms=2.5).tolist()
        [[0, 2], [2, 4], [4, 4]]
    """
    window_us, stride_us = _time_geometry(window_ms, stride_ms)
    index = TimeWindowIndex(window_us, stride_us, start_us)
    return np.concatenate([index.add(t_us), index.finish()])


def window_ranges_by_count(n_events: int, events_per_window: int, stride: int | None = None) -> np.ndarray:
    """Index ranges of windows of ``events_per_window`` events, as :class:`CountWindowIndex` cuts them.

    Windows start every ``stride`` events: every full window, then one last window of the events left
    from the next start on, if any.

    Args:
        n_events: number of events.
        events_per_window: events per window.
        stride: step between the windows' first events; defaults to ``events_per_window``.

    Returns:
        int64 array :math:`(M, 2)` of ``[begin, end)`` event indices.

    Raises:
        EventFormatError: a window size or stride that is not a positive whole number, or a negative
            ``n_events``.

    Examples:
        >>> window_ranges_by_count(10, 4, stride=3).tolist()
        [[0, 4], [3, 7], [6, 10], [9, 10]]
    """
    stride = None if stride is None else _positive_whole(stride, "stride")
    index = CountWindowIndex(events_per_window, stride)
    return np.concatenate([index.add(n_events), index.finish()])


class TimeWindowIndex:
    """``[begin, end)`` event indices of time windows, found chunk by chunk while a stream passes.

    Window ``i`` covers the timestamps ``[start + i*stride, start + i*stride + window)``; the windows are
    those that start at or before the stream's last timestamp, empty ones (gaps) included. A window is
    complete once an event at or after its end has arrived, and :meth:`add` returns it then; the windows
    still open at the end of the stream come from :meth:`finish`, which ends the stream.

    A window start or end first reached in a chunk lies after every earlier event, so its index is the
    count of earlier events plus one ``searchsorted`` within the chunk: each chunk costs what its own
    length and the windows it reaches cost, whatever came before.

    Args:
        window_us: window length in microseconds.
        stride_us: step between window starts; defaults to ``window_us`` (no overlap).
        start_us: start of window 0; defaults to the stream's first timestamp.

    Attributes:
        start_us: start of window 0 (``None`` until the first event when not given).
        n_events: events added so far.
        n_windows: windows returned so far.

    Raises:
        EventFormatError: a window or stride that is not a positive whole number of microseconds.

    Examples:
        >>> index = TimeWindowIndex(window_us=10, stride_us=5)
        >>> index.add(np.array([0, 3, 8, 12])).tolist()  # 12 closes [0, 10)
        [[0, 3]]
        >>> index.add(np.array([16, 40])).tolist()  # 40 closes the windows up to [30, 40)
        [[2, 4], [3, 5], [4, 5], [5, 5], [5, 5], [5, 5]]
        >>> index.finish().tolist()  # [35, 45) and [40, 50) end with the stream
        [[5, 6], [5, 6]]
    """

    def __init__(self, window_us: int, stride_us: int | None = None, start_us: int | None = None) -> None:
        self.window_us = _positive_whole(window_us, "window_us")
        self.stride_us = self.window_us if stride_us is None else _positive_whole(stride_us, "stride_us")
        self.start_us = None if start_us is None else _whole(start_us, "start_us")
        self.n_events, self.n_windows = 0, 0
        self._open = np.zeros(0, dtype=np.int64)  # begins of the windows started but not yet complete
        self._last_us = None

    @property
    def needed_from(self) -> int:
        """Index of the first event a window not yet returned may hold; no later window needs those before."""
        return int(self._open[0]) if len(self._open) else self.n_events

    def add(self, t_us: np.ndarray) -> np.ndarray:
        """Index the stream's next chunk of timestamps.

        Args:
            t_us: the chunk's integer timestamps in microseconds, :math:`(n,)`, non-decreasing and at
                or after those of earlier chunks.

        Returns:
            int64 :math:`(K, 2)`, ``[begin, end)`` in the whole stream of the windows this chunk completes.

        Raises:
            EventFormatError: timestamps not 1-D, or that decrease, within the chunk or from the previous
                one.
        """
        t_us = np.asarray(t_us)
        if t_us.ndim != 1:
            raise EventFormatError(f"timestamps must be a 1-D array (n,), got shape {t_us.shape}")
        if len(t_us) == 0:
            return np.zeros((0, 2), dtype=np.int64)
        _check_sorted(t_us, self._last_us, self.n_events)
        if self.start_us is None:
            self.start_us = int(t_us[0])
        last = int(t_us[-1])
        started = self.n_windows + len(self._open)
        starts = self._starts(started, self._windows_starting_by(last))
        self._open = np.concatenate([self._open, self.n_events + np.searchsorted(t_us, starts, side="left")])
        complete = self._windows_starting_by(last - self.window_us)
        ends = self._starts(self.n_windows, complete) + self.window_us
        ranges = np.column_stack(
            [self._open[: len(ends)], self.n_events + np.searchsorted(t_us, ends, side="left")]
        )
        self._open = self._open[len(ends) :]
        self.n_events, self.n_windows, self._last_us = self.n_events + len(t_us), complete, last
        return ranges.astype(np.int64, copy=False)

    def finish(self) -> np.ndarray:
        """The windows still open at the end of the stream, int64 :math:`(K, 2)`; each ends with it."""
        ranges = np.column_stack([self._open, np.full(len(self._open), self.n_events, dtype=np.int64)])
        self.n_windows += len(self._open)
        self._open = self._open[:0]
        return ranges

    def _windows_starting_by(self, t_us: int) -> int:
        """How many windows start at or before ``t_us``."""
        return max(0, (t_us - self.start_us) // self.stride_us + 1)

    def _starts(self, first: int, stop: int) -> np.ndarray:
        return self.start_us + self.stride_us * np.arange(first, stop, dtype=np.int64)


class CountWindowIndex:
    """``[begin, end)`` event indices of windows of an event count, found chunk by chunk.

    Window ``i`` holds events ``[i*stride, i*stride + events_per_window)``. :meth:`add` returns each
    full window once its last event has arrived; :meth:`finish`, which ends the stream, returns one last
    window of the events left from the next start on, if any: the only window that may hold fewer events.

    Args:
        events_per_window: events per window.
        stride_events: step between the windows' first events; defaults to ``events_per_window``.

    Attributes:
        n_events: events added so far.
        n_windows: windows returned so far.

    Raises:
        EventFormatError: a window size or stride that is not a positive whole number.

    Examples:
        >>> index = CountWindowIndex(events_per_window=3, stride_events=5)
        >>> index.add(7).tolist(), index.add(4).tolist(), index.finish().tolist()
        ([[0, 3]], [[5, 8]], [[10, 11]])
    """

    def __init__(self, events_per_window: int, stride_events: int | None = None) -> None:
        self.events_per_window = _positive_whole(events_per_window, "events_per_window")
        self.stride_events = (
            self.events_per_window
            if stride_events is None
            else _positive_whole(stride_events, "stride_events")
        )
        self.n_events, self.n_windows = 0, 0

    @property
    def needed_from(self) -> int:
        """Index of the next window's first event, maybe not yet arrived; no later window needs one before."""
        return self.n_windows * self.stride_events

    def add(self, n_events: int) -> np.ndarray:
        """Count the stream's next ``n_events`` events.

        Returns:
            int64 :math:`(K, 2)`, ``[begin, end)`` of the full windows these events complete.

        Raises:
            EventFormatError: ``n_events`` is not a whole number of at least 0.
        """
        n_events = _whole(n_events, "n_events")
        if n_events < 0:
            raise EventFormatError(f"n_events must be at least 0, got {n_events}")
        self.n_events += n_events
        full = max(0, (self.n_events - self.events_per_window) // self.stride_events + 1)
        begins = self.stride_events * np.arange(self.n_windows, full, dtype=np.int64)
        self.n_windows = full
        return np.column_stack([begins, begins + self.events_per_window])

    def finish(self) -> np.ndarray:
        """The last window, of the events left from the next start on, int64 :math:`(K, 2)` with K 0 or 1."""
        begin = self.needed_from
        if begin >= self.n_events:
            return np.zeros((0, 2), dtype=np.int64)
        self.n_windows += 1
        return np.array([[begin, self.n_events]], dtype=np.int64)


class Window(NamedTuple):
    """One window cut from a stream: its index, its events and the stream index of its first event."""

    index: int
    events: np.ndarray
    offset: int


def iter_windows(
    chunks: Iterable[np.ndarray],
    *,
    window_ms: float | None = None,
    stride_ms: float | None = None,
    events_per_window: int | None = None,
    stride_events: int | None = None,
) -> Iterator[Window]:
    """Cut a stream of canonical event chunks into windows, holding only what the next window needs.

    Windows are either ``window_ms`` long and start every ``stride_ms`` (default: no overlap), as
    :class:`TimeWindowIndex` cuts them, or hold ``events_per_window`` events and start every
    ``stride_events``, as :class:`CountWindowIndex` cuts them (every full window, then one last window of
    the events left). Memory stays bounded by one chunk plus one window, however long the stream.

    Args:
        chunks: canonical event arrays (:data:`EVENT_DTYPE`), consecutive pieces of one recording.

    Yields:
        :class:`Window` tuples; ``offset`` locates the window's first event in the whole stream, so
        per-window results map back to the caller's order.

    Raises:
        EventFormatError: on no window size, on both kinds at once, on a size or stride that is not
            positive, or when time runs backwards.

    Examples:
        >>> from evseg_torch.events import as_events
        >>> events = as_events(np.column_stack([np.arange(6) * 1e-3, np.zeros((6, 3))]))
        >>> chunks = [events[:4], events[4:]]
        >>> windows = iter_windows(chunks, events_per_window=2, stride_events=3)
        >>> [(w.index, w.offset, len(w.events)) for w in windows]
        [(0, 0, 2), (1, 3, 2)]
    """
    if (window_ms is None) == (events_per_window is None):
        raise EventFormatError("give exactly one of window_ms and events_per_window")
    by_time = window_ms is not None
    if by_time:
        index = TimeWindowIndex(*_time_geometry(window_ms, stride_ms))
    else:
        index = CountWindowIndex(events_per_window, stride_events)
    buffer, buffer_offset = np.zeros(0, dtype=EVENT_DTYPE), 0
    for chunk in _checked_chunks(chunks):
        buffer = np.concatenate([buffer, chunk])
        yield from _cut(buffer, buffer_offset, index.add(chunk["t"] if by_time else len(chunk)), index)
        # The next window may start past the buffer's end (a count stride longer than the window),
        # so the drop stops there and the offset stays that of the buffer's first event.
        drop = min(index.needed_from - buffer_offset, len(buffer))
        buffer, buffer_offset = buffer[drop:], buffer_offset + drop
    yield from _cut(buffer, buffer_offset, index.finish(), index)


def _whole(value, name: str) -> int:
    try:
        whole = not isinstance(value, bool) and float(value).is_integer()
    except (TypeError, ValueError):
        whole = False
    if not whole:
        raise EventFormatError(f"{name} must be a whole number, got {value!r}")
    return int(value)


def _positive_whole(value, name: str) -> int:
    whole = _whole(value, name)
    if whole <= 0:
        raise EventFormatError(f"{name} must be a positive whole number, got {value!r}")
    return whole


def _time_geometry(window_ms: float, stride_ms: float | None) -> tuple[int, int]:
    """``(window_us, stride_us)``; the stride defaults to the window."""
    window_us = _positive_us(window_ms, "window_ms")
    return window_us, window_us if stride_ms is None else _positive_us(stride_ms, "stride_ms")


def _cut(
    buffer: np.ndarray, buffer_offset: int, ranges: np.ndarray, index: TimeWindowIndex | CountWindowIndex
) -> Iterator[Window]:
    """The windows at stream indices ``ranges`` :math:`(K, 2)`, the last K of ``index``, from ``buffer``."""
    first = index.n_windows - len(ranges)
    for number, (begin, end) in enumerate(ranges.tolist(), start=first):
        yield Window(number, buffer[begin - buffer_offset : end - buffer_offset].copy(), begin)


def _check_sorted(t_us: np.ndarray, last_us: int | None, n_before: int) -> None:
    """Raise unless ``t_us`` :math:`(n,)` is non-decreasing and starts at or after ``last_us``."""
    if last_us is not None and t_us[0] < last_us:
        raise EventFormatError(f"timestamps decrease between chunks ({last_us} us then {t_us[0]} us)")
    backwards = t_us[1:] < t_us[:-1]  # a comparison, not np.diff, which can overflow on huge spans
    if np.any(backwards):
        first = int(np.argmax(backwards)) + 1
        raise EventFormatError(
            f"timestamps decrease at event {n_before + first} ({t_us[first - 1]} us then {t_us[first]} us)"
        )


def _checked_chunks(chunks: Iterable[np.ndarray]) -> Iterator[np.ndarray]:
    last, n_before = None, 0
    for chunk in chunks:
        if chunk.dtype != EVENT_DTYPE:
            raise EventFormatError(
                f"stream chunks must be canonical events of dtype {EVENT_DTYPE}, got {chunk.dtype}"
            )
        if len(chunk) == 0:
            continue
        _check_sorted(chunk["t"], last, n_before)
        last, n_before = int(chunk["t"][-1]), n_before + len(chunk)
        yield chunk


def _positive_us(milliseconds: float, name: str) -> int:
    try:
        value = round(float(milliseconds) * 1000)
    except (TypeError, ValueError, OverflowError):
        raise EventFormatError(
            f"{name} must be a positive number of milliseconds, got {milliseconds!r}"
        ) from None
    if value <= 0:
        raise EventFormatError(f"{name} must be positive, got {milliseconds}")
    return value

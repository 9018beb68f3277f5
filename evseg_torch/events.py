"""The canonical event form, its validation, windowing and conversion to torch.

At rest and at every I/O boundary, events are a NumPy structured array of dtype :data:`EVENT_DTYPE`:

=====  ========  ==============================================================
field  dtype     meaning
=====  ========  ==============================================================
``t``  int64     timestamp in microseconds (any origin), non-decreasing
``x``  int16     pixel column, ``0 <= x < W``
``y``  int16     pixel row, ``0 <= y < H``
``p``  int8      polarity, ``-1`` (OFF) or ``+1`` (ON)
=====  ========  ==============================================================

The field names follow tonic, aedat and faery; what differs from them: tonic stores ``p`` as bool and
``(W, H, P)`` sensor sizes, aedat/faery call the polarity ``on`` (bool) and store ``t`` as uint64. All
of these are accepted by :func:`as_events`. Image sizes are ``(H, W)`` everywhere in evseg_torch.

Inside torch, one window's events are an :class:`EventBatch`: ``xy`` float (N, 2) in pixels, ``t``
float32 seconds relative to a reference time (absolute microseconds in float32 would lose
sub-millisecond precision after a few seconds), ``p`` float (N,).

Timestamps that decrease are rejected, not sorted: an event stream out of order is a defect of the
recording or the reader, and results are always reported in the caller's order, so a silent sort
would hide the defect. Sort first with ``events[np.argsort(events["t"], kind="stable")]``.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator, Sequence
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from evseg_torch.errors import EventFormatError

if TYPE_CHECKING:  # torch is imported lazily so that level one (NumPy) never loads it
    import torch

EVENT_DTYPE = np.dtype([("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "i1")])

_POLARITY_FIELDS = ("p", "on", "polarity")
_MAX_COORDINATE = np.iinfo(np.int16).max
_MAX_SECONDS = 9.2e12  # |t| * 1e6 must stay below 2^63 microseconds


def as_events(data, sensor_size: tuple[int, int] | None = None) -> np.ndarray:
    """Validate events and return them in the canonical form, as a new array.

    Args:
        data: either a structured array with integer field ``t`` (microseconds) and fields ``x``,
            ``y`` and one of ``p``/``on``/``polarity``; or a float/int array of shape :math:`(N, 4)`
            with columns ``[t_seconds, x, y, p]``. Polarity may be {0, 1}, {-1, +1} or bool.
        sensor_size: ``(H, W)``; when given, every event must lie inside it.

    Returns:
        A new structured array of dtype :data:`EVENT_DTYPE`, shape :math:`(N,)`. The input is never
        modified, and never returned itself.

    Raises:
        EventFormatError: wrong shape or dtype, NaN or inf, non-integer or out-of-sensor coordinates,
            polarity outside {-1, 0, 1}, decreasing timestamps, or no events at all.

    Examples:
        >>> ev = as_events(np.array([[0.0, 3, 4, 1], [0.001, 5, 6, 0]]), sensor_size=(10, 10))
        >>> ev["t"].tolist(), ev["p"].tolist()
        ([0, 1000], [1, -1])
    """
    t_us, x, y, p = _columns(data)
    if t_us.shape[0] == 0:
        raise EventFormatError("no events: the input holds 0 events")
    x = _pixel_coordinates(x, "x")
    y = _pixel_coordinates(y, "y")
    if sensor_size is not None:
        height, width = check_sensor_size(sensor_size)
        _check_inside(x, width, "x", "W")
        _check_inside(y, height, "y", "H")
    backwards = t_us[1:] < t_us[:-1]  # a comparison, not np.diff, which can overflow on huge spans
    if np.any(backwards):
        first = int(np.argmax(backwards)) + 1
        raise EventFormatError(
            f"timestamps decrease at event {first} ({t_us[first - 1]} us then {t_us[first]} us); "
            "sort the events by time first, e.g. events[np.argsort(events['t'], kind='stable')]"
        )
    events = np.empty(t_us.shape[0], dtype=EVENT_DTYPE)
    events["t"] = t_us
    events["x"] = x
    events["y"] = y
    events["p"] = _polarity(p)
    return events


def check_sensor_size(sensor_size) -> tuple[int, int]:
    """Return ``(H, W)`` as ints, or raise :class:`EventFormatError` naming what is wrong."""
    try:
        height, width = (v.item() if isinstance(v, np.generic | np.ndarray) else v for v in sensor_size)
    except (TypeError, ValueError):
        raise EventFormatError(f"sensor_size must be (H, W), got {sensor_size!r}") from None
    for value in (height, width):
        if isinstance(value, bool) or not isinstance(value, int | float) or value != int(value):
            raise EventFormatError(f"sensor_size (H, W) must be whole numbers, got {height!r} x {width!r}")
    height, width = int(height), int(width)
    if not (0 < height <= _MAX_COORDINATE + 1 and 0 < width <= _MAX_COORDINATE + 1):
        raise EventFormatError(
            f"sensor_size (H, W) must be positive and at most 32768, got {height} x {width}"
        )
    return height, width


def sensor_size_from_tonic(sensor_size: tuple[int, int, int]) -> tuple[int, int]:
    """Convert tonic's ``(W, H, P)`` sensor size to evseg_torch's ``(H, W)``."""
    width, height, _ = sensor_size
    return int(height), int(width)


def sensor_size_to_tonic(sensor_size: tuple[int, int], polarities: int = 2) -> tuple[int, int, int]:
    """Convert evseg_torch's ``(H, W)`` sensor size to tonic's ``(W, H, P)``."""
    height, width = check_sensor_size(sensor_size)
    return width, height, polarities


def infer_sensor_size(events: np.ndarray) -> tuple[int, int]:
    """The smallest ``(H, W)`` that holds every event of a canonical array."""
    return int(events["y"].max()) + 1, int(events["x"].max()) + 1


def to_array(events: np.ndarray) -> np.ndarray:
    """Canonical events as a float64 array :math:`(N, 4)` with columns ``[t_seconds, x, y, p]``."""
    return np.column_stack([events["t"] * 1e-6, events["x"], events["y"], events["p"]]).astype(np.float64)


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


class EventBatch(NamedTuple):
    """Events as torch tensors: one window, or a padded batch of windows.

    One window: ``xy`` :math:`(N, 2)`, ``t`` :math:`(N,)`, ``p`` :math:`(N,)` and ``lengths`` ``None``.
    A batch of B windows (the one batch form of evseg_torch, built by :func:`batch_windows`): each field
    gains a leading batch dimension and is padded to the longest window, ``xy`` :math:`(B, N_{max}, 2)`,
    ``t`` and ``p`` :math:`(B, N_{max})`, and ``lengths`` int64 :math:`(B,)` counts each window's real
    events; padding sits at the end of each row, with every field 0 there (``p`` = 0 is no polarity).

    Attributes:
        xy: pixel coordinates, ``x`` the column and ``y`` the row.
        t: seconds relative to each window's reference time.
        p: polarity in {-1, +1} (0 for padding).
        lengths: events per window of a batch; ``None`` for one window.

    ``len()`` is the size of the first dimension: the number of events of one window, the number of
    windows of a batch.
    """

    xy: torch.Tensor
    t: torch.Tensor
    p: torch.Tensor
    lengths: torch.Tensor | None = None

    @property
    def is_batched(self) -> bool:
        """Whether this is a padded batch of windows."""
        return self.lengths is not None

    @property
    def mask(self) -> torch.Tensor:
        """Which entries are real events (bool): :math:`(B, N_{max})` for a batch, :math:`(N,)` else."""
        import torch

        if self.lengths is None:
            return torch.ones(self.t.shape, dtype=torch.bool, device=self.t.device)
        return torch.arange(self.t.shape[-1], device=self.t.device) < self.lengths[:, None]

    def to(self, *args, **kwargs) -> EventBatch:
        """Move or cast the event tensors, as :meth:`torch.Tensor.to` does; ``lengths`` only moves."""
        xy, t, p = (tensor.to(*args, **kwargs) for tensor in (self.xy, self.t, self.p))
        lengths = None if self.lengths is None else self.lengths.to(device=xy.device)
        return EventBatch(xy, t, p, lengths)

    def unbatch(self) -> list[EventBatch]:
        """The windows of a batch, each without its padding (views, not copies)."""
        if self.lengths is None:
            raise EventFormatError("unbatch needs a padded batch of windows (lengths given), got one window")
        return [
            EventBatch(self.xy[row, :count], self.t[row, :count], self.p[row, :count])
            for row, count in enumerate(self.lengths.tolist())
        ]

    def __len__(self) -> int:  # a NamedTuple's len would be 4, the number of fields
        return int(self.t.shape[0])


def _make_event_batch(cls, iterable) -> EventBatch:
    fields = tuple(iterable)
    if len(fields) != len(cls._fields):
        raise TypeError(f"EventBatch takes {len(cls._fields)} fields, got {len(fields)}")
    return tuple.__new__(cls, fields)


# NamedTuple's own _make, behind _replace, checks len() against the 4 fields, which __len__ changed; a
# NamedTuple's class body may not redefine it.
EventBatch._make = classmethod(_make_event_batch)


def batch_windows(windows: Sequence[EventBatch]) -> EventBatch:
    """Pad windows into one batch (see :class:`EventBatch`).

    Args:
        windows: B single windows, all of one dtype and on one device.

    Returns:
        The padded batch, ``lengths`` the windows' event counts.

    Raises:
        EventFormatError: no windows, a window that is itself a batch, or windows whose fields are not
            ``xy`` :math:`(N, 2)`, ``t`` and ``p`` :math:`(N,)`.

    Examples:
        >>> import torch
        >>> one = EventBatch(torch.zeros(3, 2), torch.zeros(3), torch.ones(3))
        >>> two = EventBatch(torch.ones(1, 2), torch.zeros(1), -torch.ones(1))
        >>> batch = batch_windows([one, two])
        >>> batch.xy.shape, batch.lengths.tolist(), batch.p[1].tolist()
        (torch.Size([2, 3, 2]), [3, 1], [-1.0, 0.0, 0.0])
    """
    import torch

    windows = list(windows)
    if not windows:
        raise EventFormatError("batch_windows needs at least one window, got none")
    for index, window in enumerate(windows):
        if not isinstance(window, EventBatch) or window.is_batched:
            raise EventFormatError(f"window {index} is not a single EventBatch window")
        count = len(window)
        if window.xy.shape != (count, 2) or window.p.shape != (count,) or window.t.ndim != 1:
            raise EventFormatError(
                f"window {index} must have xy (N, 2), t (N,), p (N,); got {tuple(window.xy.shape)}, "
                f"{tuple(window.t.shape)}, {tuple(window.p.shape)}"
            )
    first = windows[0]
    lengths = torch.tensor([len(window) for window in windows], dtype=torch.int64, device=first.t.device)
    longest = int(lengths.max()) if len(windows) else 0
    xy = first.xy.new_zeros(len(windows), longest, 2)
    t = first.t.new_zeros(len(windows), longest)
    p = first.p.new_zeros(len(windows), longest)
    for row, window in enumerate(windows):
        count = len(window)
        xy[row, :count], t[row, :count], p[row, :count] = window.xy, window.t, window.p
    return EventBatch(xy, t, p, lengths)


def batch_of_one(events: EventBatch) -> EventBatch:
    """One window as a padded batch of one window (views of its tensors, ``lengths`` its event count)."""
    import torch

    lengths = torch.tensor([events.t.shape[-1]], device=events.t.device)
    return EventBatch(events.xy[None], events.t[None], events.p[None], lengths)


def to_torch(
    events: np.ndarray,
    t_ref_us: int | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> EventBatch:
    """Convert canonical events to an :class:`EventBatch`.

    Args:
        events: canonical structured array :math:`(N,)` (see :func:`as_events`).
        t_ref_us: reference time in microseconds; defaults to the first event's timestamp.
        device: torch device of the output.
        dtype: floating dtype of the output; defaults to float32.

    Returns:
        :class:`EventBatch` with ``t`` in seconds relative to ``t_ref_us`` (computed in int64 first,
        so no precision is lost to float32 absolute times).
    """
    import torch

    dtype = dtype or torch.float32
    if events.dtype != EVENT_DTYPE:
        raise EventFormatError(
            f"to_torch expects canonical events of dtype {EVENT_DTYPE}, got {events.dtype}"
        )
    t_ref = int(events["t"][0]) if t_ref_us is None and len(events) else int(t_ref_us or 0)
    t_rel = (events["t"] - t_ref).astype(np.float64) * 1e-6
    xy = np.column_stack([events["x"], events["y"]])
    return EventBatch(
        xy=torch.as_tensor(xy, dtype=dtype, device=device),
        t=torch.as_tensor(t_rel, dtype=dtype, device=device),
        p=torch.as_tensor(events["p"], dtype=dtype, device=device),
    )


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


def _columns(data) -> tuple[np.ndarray, ...]:
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(data, torch.Tensor):
        raise EventFormatError("events must be a NumPy array; convert tensors with tensor.cpu().numpy()")
    if not isinstance(data, np.ndarray):
        try:
            data = np.asarray(data)
        except (TypeError, ValueError) as err:
            raise EventFormatError(f"events must be an array, got {type(data).__name__}: {err}") from None
    if data.dtype.names is not None:
        return _structured_columns(data)
    if data.ndim != 2 or data.shape[1] != 4:
        raise EventFormatError(
            "events must be an (N, 4) array [t_seconds, x, y, p] or a structured array, "
            f"got shape {data.shape}"
        )
    if not (np.issubdtype(data.dtype, np.floating) or np.issubdtype(data.dtype, np.integer)):
        raise EventFormatError(f"(N, 4) events must be numeric, got dtype {data.dtype}")
    values = data.astype(np.float64)
    if not np.all(np.isfinite(values)):
        bad = int(np.argmax(~np.all(np.isfinite(values), axis=1)))
        raise EventFormatError(f"events hold NaN or inf (first at row {bad})")
    if np.any(np.abs(values[:, 0]) >= _MAX_SECONDS):
        raise EventFormatError(f"timestamps beyond +-{_MAX_SECONDS:.3g} s do not fit int64 microseconds")
    t_us = np.rint(values[:, 0] * 1e6).astype(np.int64)
    return t_us, values[:, 1], values[:, 2], values[:, 3]


def _structured_columns(data: np.ndarray) -> tuple[np.ndarray, ...]:
    names = data.dtype.names
    polarity = next((name for name in _POLARITY_FIELDS if name in names), None)
    missing = [name for name in ("t", "x", "y") if name not in names] + ([] if polarity else ["p"])
    if missing:
        raise EventFormatError(f"structured events lack field(s) {missing}; they have {list(names)}")
    if data.ndim != 1:
        raise EventFormatError(f"structured events must be 1-D, got shape {data.shape}")
    if not np.issubdtype(data.dtype["t"], np.integer):
        raise EventFormatError(
            f"structured field t must be integer microseconds, got {data.dtype['t']}; "
            "pass seconds as an (N, 4) float array [t_seconds, x, y, p] instead"
        )
    t = data["t"]
    if t.dtype.kind == "u" and t.size and t.max() > np.iinfo(np.int64).max:
        raise EventFormatError("timestamps of 2^63 us or more do not fit int64 microseconds")
    columns = [data["x"], data["y"], data[polarity]]
    for name, column in zip(("x", "y", polarity), columns, strict=True):
        if column.dtype.kind == "f" and not np.all(np.isfinite(column)):
            raise EventFormatError(f"field {name} holds NaN or inf")
    return (data["t"].astype(np.int64), *columns)


def _pixel_coordinates(values: np.ndarray, name: str) -> np.ndarray:
    values = np.asarray(values)
    if values.dtype.kind == "f" and np.any(values != np.floor(values)):
        raise EventFormatError(f"{name} holds non-integer pixel coordinates; events sit on pixels")
    if values.dtype.kind not in "fiub":
        raise EventFormatError(f"{name} must be numeric, got dtype {values.dtype}")
    if np.any(values < 0):
        raise EventFormatError(f"{name} holds negative coordinates (min {values.min()})")
    if np.any(values > _MAX_COORDINATE):
        raise EventFormatError(f"{name} holds coordinates beyond {_MAX_COORDINATE} (max {values.max()})")
    return values.astype(np.int16)


def _check_inside(values: np.ndarray, size: int, name: str, size_name: str) -> None:
    if np.any(values >= size):
        raise EventFormatError(
            f"{name} = {int(values.max())} lies outside the sensor ({size_name} = {size}); "
            "check sensor_size (H, W)"
        )


def _polarity(p: np.ndarray) -> np.ndarray:
    p = np.asarray(p)
    if p.dtype == np.bool_:
        return np.where(p, 1, -1).astype(np.int8)
    valid = (p == 0) | (p == 1) | (p == -1)
    if not np.all(valid):
        bad = p[~valid][0]
        raise EventFormatError(f"polarity must be in {{0, 1}}, {{-1, +1}} or bool, found {bad!r}")
    return np.where(p > 0, 1, -1).astype(np.int8)


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

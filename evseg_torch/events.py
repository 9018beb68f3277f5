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
        height, width = (int(v) for v in sensor_size)
    except (TypeError, ValueError):
        raise EventFormatError(f"sensor_size must be (H, W), got {sensor_size!r}") from None
    if not (0 < height <= _MAX_COORDINATE + 1 and 0 < width <= _MAX_COORDINATE + 1):
        raise EventFormatError(f"sensor_size (H, W) must be positive and at most 32768, got {sensor_size!r}")
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
    """Index ranges of fixed-duration windows over sorted timestamps.

    Window ``i`` covers ``[start + i*stride, start + i*stride + window)``. Only windows that start
    at or before the last timestamp are returned, so a stream can be processed chunk by chunk by
    passing each chunk's timestamps with an explicit ``start_us``.

    Args:
        t_us: sorted timestamps in microseconds, :math:`(N,)`.
        window_ms: window length in milliseconds.
        stride_ms: step between window starts; defaults to ``window_ms`` (no overlap).
        start_us: start of the first window; defaults to the first timestamp.

    Returns:
        int64 array :math:`(M, 2)` of ``[begin, end)`` indices into ``t_us``.
    """
    window_us, stride_us = (
        _positive_us(window_ms, "window_ms"),
        _positive_us(stride_ms or window_ms, "stride_ms"),
    )
    t_us = np.asarray(t_us)
    if t_us.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    start = int(t_us[0]) if start_us is None else int(start_us)
    count = max(0, (int(t_us[-1]) - start) // stride_us + 1)
    starts = start + stride_us * np.arange(count, dtype=np.int64)
    begin = np.searchsorted(t_us, starts, side="left")
    end = np.searchsorted(t_us, starts + window_us, side="left")
    return np.column_stack([begin, end]).astype(np.int64)


def window_ranges_by_count(n_events: int, events_per_window: int, stride: int | None = None) -> np.ndarray:
    """Index ranges of windows of ``events_per_window`` events, starting every ``stride`` events.

    The last window may be shorter. Returns an int64 array :math:`(M, 2)` of ``[begin, end)``.
    """
    if int(events_per_window) <= 0:
        raise EventFormatError(f"events_per_window must be positive, got {events_per_window}")
    stride = int(stride or events_per_window)
    if stride <= 0:
        raise EventFormatError(f"stride must be positive, got {stride}")
    begin = np.arange(0, max(int(n_events), 0), stride, dtype=np.int64)
    end = np.minimum(begin + int(events_per_window), n_events)
    return np.column_stack([begin, end]).astype(np.int64)


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

    Windows are either ``window_ms`` long and start every ``stride_ms`` (default: no overlap), or hold
    ``events_per_window`` events and start every ``stride_events``. Memory stays bounded by one chunk
    plus one window, however long the stream. The chunks must continue each other in time.

    Args:
        chunks: canonical event arrays (:data:`EVENT_DTYPE`), consecutive pieces of one recording.

    Yields:
        :class:`Window` tuples; ``offset`` locates the window's first event in the whole stream, so
        per-window results map back to the caller's order.

    Raises:
        EventFormatError: on no window size, on both kinds at once, or when time runs backwards
            between chunks.
    """
    if (window_ms is None) == (events_per_window is None):
        raise EventFormatError("give exactly one of window_ms and events_per_window")
    buffer = np.zeros(0, dtype=EVENT_DTYPE)
    buffer_offset, index, next_start = 0, 0, None
    if window_ms is not None:
        window_us = _positive_us(window_ms, "window_ms")
        stride_us = _positive_us(stride_ms or window_ms, "stride_ms")
    else:
        size = _whole(events_per_window, "events_per_window")
        stride = size if stride_events is None else _whole(stride_events, "stride_events")
        if size <= 0 or stride <= 0:
            raise EventFormatError(f"events_per_window and its stride must be positive, got {size}, {stride}")
    for chunk in _checked_chunks(chunks):
        buffer = np.concatenate([buffer, chunk])
        if window_ms is not None:
            next_start = int(buffer["t"][0]) if next_start is None else next_start
            # A window is complete once an event at or after its end has arrived.
            while len(buffer) and buffer["t"][-1] >= next_start + window_us:
                yield _time_window(buffer, buffer_offset, index, next_start, window_us)
                index, next_start = index + 1, next_start + stride_us
                drop = int(np.searchsorted(buffer["t"], next_start, side="left"))
                buffer, buffer_offset = buffer[drop:], buffer_offset + drop
        else:
            while len(buffer) >= size:
                yield Window(index, buffer[:size].copy(), buffer_offset)
                index += 1
                buffer, buffer_offset = buffer[stride:], buffer_offset + stride
    if window_ms is not None:
        while next_start is not None and len(buffer) and buffer["t"][-1] >= next_start:
            yield _time_window(buffer, buffer_offset, index, next_start, window_us)
            index, next_start = index + 1, next_start + stride_us
            drop = int(np.searchsorted(buffer["t"], next_start, side="left"))
            buffer, buffer_offset = buffer[drop:], buffer_offset + drop
    elif len(buffer):
        yield Window(index, buffer.copy(), buffer_offset)


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


def _time_window(buffer: np.ndarray, offset: int, index: int, start: int, length: int) -> Window:
    begin, end = np.searchsorted(buffer["t"], [start, start + length], side="left")
    return Window(index, buffer[begin:end].copy(), offset + int(begin))


def _checked_chunks(chunks: Iterable[np.ndarray]) -> Iterator[np.ndarray]:
    last = None
    for chunk in chunks:
        if chunk.dtype != EVENT_DTYPE:
            raise EventFormatError(
                f"stream chunks must be canonical events of dtype {EVENT_DTYPE}, got {chunk.dtype}"
            )
        if len(chunk) == 0:
            continue
        if last is not None and chunk["t"][0] < last:
            raise EventFormatError(f"timestamps decrease between chunks ({last} us then {chunk['t'][0]} us)")
        last = int(chunk["t"][-1])
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

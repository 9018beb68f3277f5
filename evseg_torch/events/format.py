"""The canonical event form and its validation, and conversions to other libraries' forms.

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

Timestamps that decrease are rejected, not sorted: an event stream out of order is a defect of the
recording or the reader, and results are always reported in the caller's order, so a silent sort
would hide the defect. Sort first with ``events[np.argsort(events["t"], kind="stable")]``.
"""

from __future__ import annotations

import sys

import numpy as np

from evseg_torch.errors import EventFormatError

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

"""Readers of NumPy ``.npy`` and ``.npz`` event files.

``.npy``: a float or int array :math:`(N, 4)` with columns ``[t_seconds, x, y, p]``, or a structured
array with integer field ``t`` in microseconds, ``x``, ``y`` and ``p``/``on``/``polarity`` (e.g. the
Prophesee sample decoded by expelliarmus). It is memory-mapped, so chunks stream from disk.

``.npz``, one of these layouts:

====================  ===============================================================  ============
layout                keys                                                             time
====================  ===============================================================  ============
pydvs / EV-IMO        ``events`` :math:`(N, 4)` ``[t, x, y, p]`` (+ K, D, index, ...)  seconds
columns (EED, ECD)    ``t_us``, ``x``, ``y``, ``p`` (+ ``width``, ``height``)          microseconds
CeleX (EV-MotionSeg)  ``t_raw``, ``x``, ``y``, no polarity (+ width, height)           microseconds
single array          one array :math:`(N, 4)` under any name                          seconds
====================  ===============================================================  ============

EV-IMO's files also hold ``discretization``, ``mask`` and ``meta`` (read by :mod:`~evseg_torch.io.evimo`).

The CeleX recording's README leaves the unit of ``t_raw`` undocumented but consistent with
microseconds (93 packets of ~30 ms span 3.0 s); it is read as microseconds, and as the sensor
reports no polarity, every event gets ``p = +1``.

The sensor size is ``(height, width)`` when the file stores ``width`` and ``height``, the last two
axes of ``mask`` in the EV-IMO layout, else unknown. npz members cannot be memory-mapped, so each
needed column is loaded whole and then cut into chunks. Pickled members are never loaded.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from evseg_torch.errors import ReaderError

WHAT_NPY = "NumPy .npy events file"
WHAT_NPZ = "NumPy .npz events file"

_LAYOUTS_HELP = (
    "expected 'events' (N, 4) [t_s, x, y, p], columns 't_us', 'x', 'y', 'p', "
    "columns 't_raw', 'x', 'y' (CeleX), or a single (N, 4) array"
)


def read_npy(path: Path) -> np.ndarray:
    """The whole ``.npy`` file, memory-mapped; :func:`~evseg_torch.events.as_events` copies it."""
    return _open_npy(path)


def ends_npy(path: Path) -> np.ndarray:
    """The first and the last event, read from the memory map."""
    return np.array(_open_npy(path)[[0, -1]])


def chunks_npy(path: Path, chunk_size: int) -> Iterator[np.ndarray]:
    """Consecutive slices of at most ``chunk_size`` events, each read from the file on its own."""
    return npy_row_blocks(path, _open_npy(path), chunk_size)


def npy_row_blocks(path: Path, data: np.ndarray, chunk_size: int) -> Iterator[np.ndarray]:
    """Consecutive blocks of at most ``chunk_size`` rows of an ``.npy`` file, each read on its own.

    Plain reads rather than slices of a memory map: the pages of a map stay resident once touched, so
    a long recording's resident memory would grow with its length.

    Args:
        path: the ``.npy`` file.
        data: the file memory-mapped (``np.load(path, mmap_mode="r")``), for its shape, dtype and offset.
        chunk_size: rows per block.
    """
    if not data.flags.c_contiguous:
        for begin in range(0, len(data), chunk_size):
            yield np.array(data[begin : begin + chunk_size])
        return
    n_rows, row_shape, dtype, offset = len(data), data.shape[1:], data.dtype, data.offset
    del data
    row_items = int(np.prod(row_shape, dtype=np.int64))
    with open(path, "rb") as source:
        for begin in range(0, n_rows, chunk_size):
            rows = min(chunk_size, n_rows - begin)
            source.seek(offset + begin * row_items * dtype.itemsize)
            chunk = np.fromfile(source, dtype=dtype, count=rows * row_items)
            if chunk.size != rows * row_items:
                raise ReaderError(
                    f"the file ends after {begin + chunk.size // max(row_items, 1)} of {n_rows} rows"
                )
            yield chunk.reshape(rows, *row_shape)


def sensor_size_npy(path: Path) -> None:
    """``.npy`` files store no sensor size."""
    return None


def read_npz(path: Path) -> np.ndarray:
    """All events of the ``.npz`` file, as :math:`(N, 4)` seconds or a structured array in µs."""
    with open_npz(path) as npz:
        columns = _columns(npz)
    return _assemble(columns, slice(None))


def ends_npz(path: Path) -> np.ndarray:
    """The first and the last event (members cannot be memory-mapped: the columns are loaded)."""
    with open_npz(path) as npz:
        columns = _columns(npz)
    return _assemble(columns, np.array([0, -1]))


def chunks_npz(path: Path, chunk_size: int) -> Iterator[np.ndarray]:
    """Consecutive blocks of at most ``chunk_size`` events."""
    with open_npz(path) as npz:
        columns = _columns(npz)
    count = len(next(iter(columns.values())))
    for begin in range(0, count, chunk_size):
        yield _assemble(columns, slice(begin, begin + chunk_size))


def sensor_size_npz(path: Path) -> tuple[int, int] | None:
    """``(H, W)`` from a ``sensor_size`` member, ``height``/``width`` or an EV-IMO ``mask``'s shape, else
    ``None``; the caller checks the values."""
    with open_npz(path) as npz:
        if "sensor_size" in npz.files:
            return tuple(np.asarray(npz["sensor_size"]).tolist())
        if "width" in npz.files and "height" in npz.files:
            height, width = np.asarray(npz["height"]), np.asarray(npz["width"])
            if height.size != 1 or width.size != 1:
                raise ReaderError(
                    f"height and width must be single numbers, got shapes {height.shape}, {width.shape}"
                )
            return height.item(), width.item()
        if "mask" in npz.files:
            shape = member_shape(npz, "mask")
            if len(shape) == 3:
                return int(shape[1]), int(shape[2])
    return None


@contextmanager
def open_npz(path: Path, allow_pickle: bool = False) -> Iterator[np.lib.npyio.NpzFile]:
    """Open an npz; the file is opened here because np.load leaks its handle when the zip is corrupt."""
    with open(path, "rb") as file, np.load(file, allow_pickle=allow_pickle) as npz:
        yield npz


def member_shape(npz, key: str) -> tuple[int, ...]:
    """The shape of an npz member read from its header alone, without loading (or unpickling) it."""
    with npz.zip.open(f"{key}.npy") as member:
        version = np.lib.format.read_magic(member)
        if version == (1, 0):
            shape, _, _ = np.lib.format.read_array_header_1_0(member)
        else:
            shape, _, _ = np.lib.format.read_array_header_2_0(member)
    return tuple(shape)


def _open_npy(path: Path) -> np.ndarray:
    data = np.load(path, mmap_mode="r", allow_pickle=False)
    if data.dtype.names is None and (data.ndim != 2 or data.shape[1] != 4):
        raise ReaderError(
            f"the array has shape {data.shape} and dtype {data.dtype}; "
            "expected (N, 4) [t_seconds, x, y, p] or a structured array with fields t (us), x, y, p"
        )
    return data


def _columns(npz) -> dict[str, np.ndarray]:
    """Load the arrays of whichever layout the file has (see the module docstring)."""
    keys = set(npz.files)
    if "events" in keys or len(keys) == 1:
        name = "events" if "events" in keys else keys.pop()
        events = npz[name]
        if not isinstance(events, np.ndarray):
            raise ReaderError(f"member {name!r} is not a valid .npy array")  # NpzFile returns raw bytes
        if events.ndim != 2 or events.shape[1] != 4:
            raise ReaderError(f"{name!r} has shape {events.shape}; {_LAYOUTS_HELP}")
        return {"events": events}
    if {"t_us", "x", "y", "p"} <= keys:
        columns = {name: npz[name] for name in ("t_us", "x", "y", "p")}
        if not all(isinstance(column, np.ndarray) for column in columns.values()):
            raise ReaderError("a column member is not a valid .npy array")
    elif {"t_raw", "x", "y"} <= keys and "p" not in keys:
        columns = {"t_us": npz["t_raw"], "x": npz["x"], "y": npz["y"]}
        columns["p"] = np.ones(len(columns["t_us"]), dtype=np.int8)
    else:
        raise ReaderError(f"unknown npz layout with keys {sorted(keys)}; {_LAYOUTS_HELP}")
    lengths = {name: column.shape for name, column in columns.items()}
    if any(column.ndim != 1 for column in columns.values()) or len(set(lengths.values())) != 1:
        raise ReaderError(f"event columns must be 1-D and of one length, got shapes {lengths}")
    if not np.issubdtype(columns["t_us"].dtype, np.integer):
        raise ReaderError(f"microsecond timestamps must be integers, got dtype {columns['t_us'].dtype}")
    return columns


def _assemble(columns: dict[str, np.ndarray], rows: slice) -> np.ndarray:
    if "events" in columns:
        return columns["events"][rows]
    t_us = columns["t_us"][rows]
    dtype = [("t", np.int64), ("x", columns["x"].dtype), ("y", columns["y"].dtype), ("p", columns["p"].dtype)]
    out = np.empty(len(t_us), dtype=dtype)
    out["t"] = t_us
    for name in ("x", "y", "p"):
        out[name] = columns[name][rows]
    return out

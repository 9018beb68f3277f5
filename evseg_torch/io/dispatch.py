"""Load event files of any supported format, chosen by the file's suffix.

==============  ====================================================  =============================
suffix          format                                                sensor size stored
==============  ====================================================  =============================
``.txt``        text ``t x y p`` (rpg / ECD / EED), see :mod:`.text`   no
``.npy``        (N, 4) seconds or structured µs, see                  no
                :mod:`.numpy_files`
``.npz``        pydvs / EV-IMO, EED/ECD columns, CeleX                width/height, EV-IMO mask
``.h5 .hdf5``   event_utils or DSEC, see :mod:`.hdf5`                 event_utils sensor_resolution
``.aedat4``     iniVation AEDAT 4, see :mod:`.aedat4`                 yes
``.aedat``      jAER AEDAT 2.0 from a DVS128, see :mod:`.aedat2`      yes (128 x 128)
==============  ====================================================  =============================

Events come back in the canonical form of :func:`evseg_torch.events.as_events`. When the caller
gives no ``sensor_size``, events are checked against the size the file stores, so that
``load_events(path)`` always fits in :func:`read_sensor_size`'s ``(H, W)``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np

from evseg_torch.errors import ConfigError, EventFormatError, ReaderError
from evseg_torch.events import as_events, check_sensor_size, infer_sensor_size
from evseg_torch.io import aedat2, aedat4, hdf5, numpy_files, text
from evseg_torch.io.guard import existing_file, reading


class _Format(NamedTuple):
    what: str
    read: Callable[[Path], np.ndarray]
    chunks: Callable[[Path, int], Iterator[np.ndarray]]
    sensor_size: Callable[[Path], tuple[int, int] | None]


_HDF5 = _Format(hdf5.WHAT, hdf5.read, hdf5.chunks, hdf5.sensor_size)

_FORMATS = {
    ".txt": _Format(text.WHAT, text.read, text.chunks, text.sensor_size),
    ".npy": _Format(
        numpy_files.WHAT_NPY, numpy_files.read_npy, numpy_files.chunks_npy, numpy_files.sensor_size_npy
    ),
    ".npz": _Format(
        numpy_files.WHAT_NPZ, numpy_files.read_npz, numpy_files.chunks_npz, numpy_files.sensor_size_npz
    ),
    ".h5": _HDF5,
    ".hdf5": _HDF5,
    ".aedat4": _Format(aedat4.WHAT, aedat4.read, aedat4.chunks, aedat4.sensor_size),
    ".aedat": _Format(aedat2.WHAT, aedat2.read, aedat2.chunks, aedat2.sensor_size),
}

SUPPORTED_SUFFIXES = tuple(_FORMATS)


def load_events(path, *, sensor_size: tuple[int, int] | None = None) -> np.ndarray:
    """Read a whole event file.

    Args:
        path: the file; its suffix (see the module table) chooses the reader.
        sensor_size: ``(H, W)`` every event must lie inside; defaults to the size the file stores,
            or no check when it stores none.

    Returns:
        Canonical events, a structured array :math:`(N,)` of dtype
        :data:`~evseg_torch.events.EVENT_DTYPE` with ``t`` in µs in the file's own time base.

    Raises:
        ReaderError: the file is missing, has an unknown suffix, or is corrupt or truncated.
        EventFormatError: the events parse but are invalid, e.g. timestamps decrease or an event
            lies outside the sensor; the message starts with the path.

    Examples:
        >>> events = load_events("events.txt")  # doctest: +SKIP
        >>> events["t"][:2]  # doctest: +SKIP
        array([1519689694766017, 1519689694766018])
    """
    path, fmt = _resolve(path)
    with reading(path, fmt.what):
        size = sensor_size if sensor_size is not None else fmt.sensor_size(path)
        return as_events(fmt.read(path), size)


def iter_event_chunks(
    path, chunk_size: int = 1_000_000, *, sensor_size: tuple[int, int] | None = None
) -> Iterator[np.ndarray]:
    """Stream an event file in consecutive canonical chunks, for recordings larger than memory.

    Every format streams from disk except ``.npz``, whose members are loaded whole (zip members
    cannot be memory-mapped) and then cut. The concatenated chunks equal :func:`load_events`.

    Args:
        path: the file; its suffix chooses the reader.
        chunk_size: the most events per chunk; each chunk is non-empty and, except the last, usually
            full (a text chunk is one block of ``chunk_size`` lines, less its comment lines).
        sensor_size: as in :func:`load_events`.

    Yields:
        Canonical event arrays, in file order, with timestamps non-decreasing across chunks.

    Raises:
        ConfigError: ``chunk_size`` is not a positive integer (raised at once).
        ReaderError: missing file or unknown suffix (raised at once); corrupt or truncated content
            (raised when the bad chunk is reached).
        EventFormatError: as in :func:`load_events`, raised when the bad chunk is reached.
    """
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int | np.integer) or chunk_size <= 0:
        raise ConfigError(f"chunk_size must be a positive integer, got {chunk_size!r}")
    path, fmt = _resolve(path)
    return _validated_chunks(path, fmt, int(chunk_size), sensor_size)


def _validated_chunks(
    path: Path, fmt: _Format, chunk_size: int, sensor_size: tuple[int, int] | None
) -> Iterator[np.ndarray]:
    with reading(path, fmt.what):
        size = sensor_size if sensor_size is not None else fmt.sensor_size(path)
        start, last_t = 0, None
        for raw in fmt.chunks(path, chunk_size):
            try:
                events = as_events(raw, size)
            except EventFormatError as err:
                raise EventFormatError(f"in the chunk starting at event {start}: {err}") from None
            if last_t is not None and events["t"][0] < last_t:
                raise EventFormatError(
                    f"timestamps decrease at event {start} ({last_t} us then {events['t'][0]} us)"
                )
            yield events
            start, last_t = start + len(events), events["t"][-1]
        if start == 0:
            raise EventFormatError("no events: the file holds 0 events")


def read_sensor_size(path) -> tuple[int, int] | None:
    """The sensor size ``(H, W)`` the file stores, or ``None`` when its format stores none.

    Only headers and metadata are read, never the events.
    """
    path, fmt = _resolve(path)
    with reading(path, fmt.what):
        size = fmt.sensor_size(path)
    if size is None:
        return None
    try:
        return check_sensor_size(size)
    except EventFormatError as err:
        raise ReaderError(f"{path}: the stored sensor size is invalid: {err}") from None


def resolve_sensor_size(path, given: tuple[int, int] | None = None) -> tuple[int, int] | None:
    """The sensor size to read ``path`` with, by the one rule of evseg_torch.

    The size the file stores wins; a size given as well must equal it. When the file stores none, the
    given size is used; with neither, ``None``: the caller takes the smallest size that holds the events
    (``(max y + 1, max x + 1)``), as :func:`scan_sensor_size` finds it.

    Raises:
        EventFormatError: ``given`` is not a valid size, or differs from the stored one.
        ReaderError: as :func:`read_sensor_size`.
    """
    if given is not None:
        given = check_sensor_size(given)
    stored = read_sensor_size(path)
    if given is not None and stored is not None and given != stored:
        raise EventFormatError(
            f"{path}: the file stores a {stored[0]}x{stored[1]} sensor but {given[0]}x{given[1]} was given; "
            "leave the size out to use the stored one"
        )
    return stored or given


def scan_sensor_size(path, chunk_size: int = 1_000_000) -> tuple[int, int]:
    """The smallest sensor size ``(max y + 1, max x + 1)`` that holds the events of ``path`` (one pass).

    Raises:
        ReaderError, EventFormatError: as :func:`iter_event_chunks`.
    """
    sizes = [infer_sensor_size(chunk) for chunk in iter_event_chunks(path, chunk_size)]
    return tuple(int(v) for v in np.max(sizes, axis=0))


def _resolve(path) -> tuple[Path, _Format]:
    path = Path(path)
    fmt = _FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise ReaderError(
            f"{path}: unknown event file suffix {path.suffix!r}; supported: {', '.join(SUPPORTED_SUFFIXES)}"
        )
    return existing_file(path), fmt

"""Load event recordings of any supported format, chosen by the file's suffix or the folder's contents.

==================  ===========================================================  =============================
input               format                                                       sensor size stored
==================  ===========================================================  =============================
``.txt``            text ``t x y p`` (rpg / ECD / EED), see :mod:`.text`         no
``.npy``            (N, 4) seconds or structured µs, see :mod:`.numpy_files`     no
``.npz``            pydvs / EV-IMO, EED/ECD columns, CeleX                       width/height, EV-IMO mask
``.h5 .hdf5``       event_utils or DSEC, see :mod:`.hdf5`                        event_utils sensor_resolution
``.aedat4``         iniVation AEDAT 4, see :mod:`.aedat4`                        yes
``.aedat``          jAER AEDAT 2.0 from a DVS128, see :mod:`.aedat2`             yes (128 x 128)
``.bag``            ROS 1 bag of event arrays, see :mod:`.rosbag`                message height/width
``.raw .dat``       Prophesee EVT 2.0/3.0 RAW or DAT, see :mod:`.prophesee_raw`  header geometry or camera
ROS 2 bag folder    folder with ``metadata.yaml``, see :mod:`.rosbag`            message height/width
EVIMO2v2 folder     ``dataset_events_*.npy`` ..., see :mod:`.evimo2`             mask image size
rpg/ECD/EED folder  ``events.txt`` (+ ``images.txt``), see :mod:`.rpg_folder`    the first frame's size
==================  ===========================================================  =============================

Events come back in the canonical form of :func:`evseg_torch.events.as_events`. When the caller
gives no ``sensor_size``, events are checked against the size the file stores, so that
``load_events(path)`` always fits in :func:`read_sensor_size`'s ``(H, W)``. :func:`reader_for` names
the reader of a path without reading any events, :func:`read_time_span` the first and last timestamps
where they cost no pass over the events. Reader options (``topic``, for ROS bags) reach only
the formats that take them; giving one to another format is a :class:`ConfigError`.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np

from evseg_torch.errors import ConfigError, EventFormatError, EvsegError, ReaderError
from evseg_torch.events import as_events, check_sensor_size, infer_sensor_size
from evseg_torch.io.evimo2 import WHAT as EVIMO2_WHAT
from evseg_torch.io.evimo2 import is_sequence as is_evimo2_sequence
from evseg_torch.io.guard import existing_file, reading
from evseg_torch.io.numpy_files import WHAT_NPY, WHAT_NPZ
from evseg_torch.io.rpg_folder import WHAT as RPG_WHAT
from evseg_torch.io.rpg_folder import is_sequence as is_rpg_sequence
from evseg_torch.validation import check_integer


class _Format(NamedTuple):
    """A reader: its module of :mod:`evseg_torch.io`, imported on first use, so that ``import evseg_torch``
    needs none of the optional packages (``needs``) that some readers use."""

    what: str
    module: str
    needs: str | None = None
    options: tuple[str, ...] = ()
    read: str = "read"
    chunks: str = "chunks"
    sensor_size: str = "sensor_size"
    ends: str | None = None  # the first and last events without a pass over the rest, where the format allows

    def function(self, name: str) -> Callable:
        """The reader's function ``name`` (``"read"``, ``"chunks"``, ``"sensor_size"`` or ``"ends"``)."""
        try:
            module = importlib.import_module(f"evseg_torch.io.{self.module}")
        except ModuleNotFoundError as err:
            if self.needs is None or (err.name or "").split(".")[0] != self.needs:
                raise
            raise ReaderError(
                f"this {self.what} needs the optional package {self.needs!r} to be read: "
                "pip install 'evseg-torch[io]'"
            ) from None
        return getattr(module, getattr(self, name))


_HDF5 = _Format("HDF5 events file", "hdf5", "h5py", ends="ends")
_ROSBAG = _Format("ROS bag", "rosbag", "rosbags", ("topic",))
_PROPHESEE = _Format("Prophesee RAW/DAT file", "prophesee_raw", "expelliarmus")
_EVIMO2 = _Format(EVIMO2_WHAT, "evimo2", ends="ends")
_RPG = _Format(RPG_WHAT, "rpg_folder", ends="ends")

_FORMATS = {
    ".txt": _Format("text events file", "text", ends="ends"),
    ".npy": _Format(
        WHAT_NPY,
        "numpy_files",
        read="read_npy",
        chunks="chunks_npy",
        sensor_size="sensor_size_npy",
        ends="ends_npy",
    ),
    ".npz": _Format(
        WHAT_NPZ,
        "numpy_files",
        read="read_npz",
        chunks="chunks_npz",
        sensor_size="sensor_size_npz",
        ends="ends_npz",
    ),
    ".h5": _HDF5,
    ".hdf5": _HDF5,
    ".aedat4": _Format("AEDAT 4 file", "aedat4", "aedat"),
    ".aedat": _Format("AEDAT 2.0 file", "aedat2"),
    ".bag": _ROSBAG,
    ".raw": _PROPHESEE,
    ".dat": _PROPHESEE,
}

SUPPORTED_SUFFIXES = tuple(_FORMATS)
SUPPORTED_FOLDERS = (
    "EVIMO2v2 sequence (dataset_events_t/xy/p.npy)",
    "ROS 2 bag (metadata.yaml)",
    "rpg / ECD / EED sequence (events.txt)",
)


def load_events(path, *, sensor_size: tuple[int, int] | None = None, topic: str | None = None) -> np.ndarray:
    """Read a whole recording.

    Args:
        path: the file or folder; its suffix or contents (see the module table) choose the reader.
        sensor_size: ``(H, W)`` every event must lie inside; defaults to the size the file stores,
            or no check when it stores none.
        topic: for a ROS bag, the topic of event arrays to read (default: the first in name order).

    Returns:
        Canonical events, a structured array :math:`(N,)` of dtype
        :data:`~evseg_torch.events.EVENT_DTYPE` with ``t`` in µs in the file's own time base.

    Raises:
        ReaderError: the file is missing, has an unknown suffix, is a folder of no known layout, or is
            corrupt or truncated.
        EventFormatError: the events parse but are invalid, e.g. timestamps decrease or an event
            lies outside the sensor; the message starts with the path.
        ConfigError: ``topic`` is given for a format other than a ROS bag, or names no event topic.

    Examples:
        >>> events = load_events("events.txt")  # doctest: +SKIP
        >>> events["t"][:2]  # doctest: +SKIP
        array([1519689694766017, 1519689694766018])
    """
    path, fmt = _resolve(path)
    options = _options(path, fmt, topic=topic)
    with reading(path, fmt.what):
        size = sensor_size if sensor_size is not None else fmt.function("sensor_size")(path, **options)
        return as_events(fmt.function("read")(path, **options), size)


def iter_event_chunks(
    path,
    chunk_size: int = 1_000_000,
    *,
    sensor_size: tuple[int, int] | None = None,
    topic: str | None = None,
) -> Iterator[np.ndarray]:
    """Stream a recording in consecutive canonical chunks, for recordings larger than memory.

    Every format streams from disk except ``.npz``, whose members are loaded whole (zip members
    cannot be memory-mapped) and then cut. The concatenated chunks equal :func:`load_events`.

    Args:
        path: the file or folder; its suffix or contents choose the reader.
        chunk_size: the most events per chunk; each chunk is non-empty and, except the last, usually
            full (a text chunk is one block of ``chunk_size`` lines, less its comment lines).
        sensor_size, topic: as in :func:`load_events`.

    Yields:
        Canonical event arrays, in file order, with timestamps non-decreasing across chunks.

    Raises:
        ConfigError: ``chunk_size`` is not a positive integer, or ``topic`` is given for a format
            other than a ROS bag (raised at once).
        ReaderError: missing file or unknown format (raised at once); corrupt or truncated content
            (raised when the bad chunk is reached).
        EventFormatError: as in :func:`load_events`, raised when the bad chunk is reached.
    """
    chunk_size = check_integer(chunk_size, "chunk_size", at_least=1)
    path, fmt = _resolve(path)
    options = _options(path, fmt, topic=topic)
    return _validated_chunks(path, fmt, chunk_size, sensor_size, options)


def _validated_chunks(
    path: Path, fmt: _Format, chunk_size: int, sensor_size: tuple[int, int] | None, options: dict
) -> Iterator[np.ndarray]:
    with reading(path, fmt.what):
        size = sensor_size if sensor_size is not None else fmt.function("sensor_size")(path, **options)
        start, last_t = 0, None
        for raw in fmt.function("chunks")(path, chunk_size, **options):
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


def read_sensor_size(path, *, topic: str | None = None) -> tuple[int, int] | None:
    """The sensor size ``(H, W)`` the file stores, or ``None`` when its format stores none.

    Only headers and metadata are read, never the events (a ROS bag's first message is decoded).
    ``topic`` as in :func:`load_events`.
    """
    path, fmt = _resolve(path)
    options = _options(path, fmt, topic=topic)
    with reading(path, fmt.what):
        size = fmt.function("sensor_size")(path, **options)
    if size is None:
        return None
    try:
        return check_sensor_size(size)
    except EventFormatError as err:
        raise ReaderError(f"{path}: the stored sensor size is invalid: {err}") from None


def resolve_sensor_size(
    path, given: tuple[int, int] | None = None, *, topic: str | None = None
) -> tuple[int, int] | None:
    """The sensor size to read ``path`` with, by the one rule of evseg_torch.

    The size the file stores wins; a size given as well must equal it. When the file stores none, the
    given size is used; with neither, ``None``: the caller takes the smallest size that holds the events
    (``(max y + 1, max x + 1)``), as :func:`scan_sensor_size` finds it.

    Raises:
        EventFormatError: ``given`` is not a valid size, or differs from the stored one.
        ReaderError, ConfigError: as :func:`read_sensor_size` (``topic`` likewise).
    """
    if given is not None:
        given = check_sensor_size(given)
    stored = read_sensor_size(path, topic=topic)
    if given is not None and stored is not None and given != stored:
        raise EventFormatError(
            f"{path}: the file stores a {stored[0]}x{stored[1]} sensor but {given[0]}x{given[1]} was given; "
            "leave the size out to use the stored one"
        )
    return stored or given


def read_time_span(path) -> tuple[int, int] | None:
    """``(first, last)`` timestamps in µs of the events of ``path``, where finding them costs no pass.

    For progress bars' totals: array files (``.npy``, ``.npz``, HDF5, an EVIMO2v2 folder's) are read at
    both ends, a text file's last line (an rpg / ECD / EED folder's ``events.txt`` too) is found from its
    end. Other formats give ``None``, as does any file these reads fail on: the reading pass itself
    reports what is wrong.

    Examples:
        >>> read_time_span("events.npy")  # doctest: +SKIP
        (0, 8000000)
    """
    try:
        path, fmt = _resolve(path)
        if fmt.ends is None:
            return None
        rows = fmt.function("ends")(path)
        if rows is None or len(rows) < 2:
            return None
        t = as_events(rows)["t"]
    except (EvsegError, OSError, ValueError, KeyError, IndexError):
        return None
    return int(t[0]), int(t[-1])


def scan_sensor_size(path, chunk_size: int = 1_000_000, *, topic: str | None = None) -> tuple[int, int]:
    """The smallest sensor size ``(max y + 1, max x + 1)`` that holds the events of ``path`` (one pass).

    Raises:
        ReaderError, EventFormatError: as :func:`iter_event_chunks`.
    """
    sizes = [infer_sensor_size(chunk) for chunk in iter_event_chunks(path, chunk_size, topic=topic)]
    return tuple(int(v) for v in np.max(sizes, axis=0))


def reader_for(path) -> str:
    """The kind of recording at ``path``, as its reader names it, without reading any events.

    For a caller (such as the command line) that checks its inputs before reading them.

    Args:
        path: a file, chosen by its suffix, or a folder, chosen by its contents.

    Returns:
        The reader's description, e.g. ``"ROS bag"`` or ``"EVIMO2v2 sequence folder"``.

    Raises:
        ReaderError: the path does not exist, has an unknown suffix, or is a folder of no known
            layout; the one-line message names the path and what is supported.

    Examples:
        >>> reader_for("recording.bag")  # doctest: +SKIP
        'ROS bag'
    """
    return _resolve(path)[1].what


def _resolve(path) -> tuple[Path, _Format]:
    path = Path(path)
    if path.is_dir():
        if is_evimo2_sequence(path):
            return path, _EVIMO2
        if (path / "metadata.yaml").is_file():  # a ROS 2 bag
            return path, _ROSBAG
        if is_rpg_sequence(path):
            return path, _RPG
        raise ReaderError(
            f"{path}: a folder of no known layout; supported folders: {'; '.join(SUPPORTED_FOLDERS)}"
        )
    fmt = _FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise ReaderError(
            f"{path}: unknown event file suffix {path.suffix!r}; supported: {', '.join(SUPPORTED_SUFFIXES)} "
            f"and folders: {'; '.join(SUPPORTED_FOLDERS)}"
        )
    return existing_file(path), fmt


def _options(path: Path, fmt: _Format, **given) -> dict:
    """The reader options that were given, checked to be ones ``fmt`` takes."""
    options = {name: value for name, value in given.items() if value is not None}
    refused = [name for name in options if name not in fmt.options]
    if refused:
        raise ConfigError(f"{path}: {', '.join(refused)} applies to ROS bags only, not to a {fmt.what}")
    return options

"""The windows of one event recording as a map-style :class:`torch.utils.data.Dataset`, read lazily.

Construction makes one streaming pass over the file (:func:`~evseg_torch.io.iter_event_chunks`): it
validates the events, writes them in canonical form (and, for a labelled file, each event's label and
ignore flag) to ``.npy`` files in a cache directory of the dataset's own, and records each window's
``[begin, end)`` event indices. A recording that already is a canonical structured ``.npy`` (dtype
:data:`~evseg_torch.events.EVENT_DTYPE`) is read in place, without a copy. The windows are cut by
:class:`~evseg_torch.events.TimeWindowIndex` or :class:`~evseg_torch.events.CountWindowIndex`, as
:func:`~evseg_torch.events.iter_windows` cuts them: exactly its windows on the same file, empty time
windows (gaps) included.

Each item reads its window's rows with plain file reads, so memory stays bounded by one chunk during the
pass and by one window per item, however long the recording. The files are not memory-mapped: the pages
of a map stay resident once touched, so a process that walks a whole recording would grow by its size.
The dataset holds only file paths and the window index, so DataLoader workers, forked or spawned, each
read the files on their own.

An item is a dict:

===============  ===========================================================================
key              value
===============  ===========================================================================
``events``       :class:`~evseg_torch.events.EventBatch` of one window, ``xy`` :math:`(N, 2)`,
                 ``t`` float32 seconds from the window's start, ``p`` :math:`(N,)`
``labels``       int64 :math:`(N,)`, each event's ground-truth label (labelled datasets only)
``ignore``       bool :math:`(N,)`, events to leave out of losses and metrics (labelled only)
``t_start_us``   int, the window's start in the recording's microseconds: the first event's
                 time plus ``index * stride`` for time windows, the window's first event's
                 time for windows of an event count
``index``        int, the window's number
``sensor_size``  ``(H, W)``
===============  ===========================================================================

Per-event labels come from a labelled ``.npz`` (the layout of ``shared/data/synthetic_probe``: a label
member and an optional ignore member beside the event columns, as
:func:`~evseg_torch.evaluation.labelled.load_labelled` reads) or from extra fields of a structured
``.npy``. EV-IMO files hold per-frame object masks, not per-event labels, so they load unlabelled
here; :mod:`evseg_torch.evaluation.evimo` scores against their masks.
"""

from __future__ import annotations

import operator
import os
import shutil
import tempfile
import weakref
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch.utils.data import Dataset

from evseg_torch.errors import ConfigError, ReaderError
from evseg_torch.events import EVENT_DTYPE, CountWindowIndex, TimeWindowIndex, to_torch
from evseg_torch.io import iter_event_chunks, resolve_sensor_size
from evseg_torch.io.guard import existing_file, reading
from evseg_torch.io.numpy_files import WHAT_NPY, WHAT_NPZ, open_npz
from evseg_torch.validation import check_integer

__all__ = ["EventWindowDataset"]


class EventWindowDataset(Dataset):
    """The windows of one recording, by time or by event count, with optional per-event labels.

    Args:
        path: an event file of any format :func:`~evseg_torch.io.load_events` reads.
        window_ms: window length in milliseconds; windows start at the first event and every
            ``stride_ms`` after it, up to the last event.
        stride_ms: step between time windows' starts; defaults to ``window_ms`` (no overlap).
        events_per_window: instead of ``window_ms``, windows of this many events, starting every
            ``stride_events`` events: every full window, then one last window of the events left from
            the next start on, if any.
        stride_events: step between count windows' first events; defaults to ``events_per_window``.
        sensor_size: ``(H, W)`` every event must lie inside. The size the file stores wins (a given one
            must equal it); with neither, the smallest that holds the events: the rule of
            :func:`~evseg_torch.io.resolve_sensor_size`, which ``evseg segment`` follows too.
        labelled: read each event's label and ignore flag too.
        label_field: the ``.npz`` member or structured ``.npy`` field of integer labels.
        ignore_field: the member or field of the ignore mask; a file without it, or ``None``, ignores
            no event.
        cache_dir: where the dataset makes its own cache directory, removed with the dataset; defaults
            to the system's temporary directory. Choose a disk, not a RAM-backed ``/tmp``, for
            recordings larger than memory.
        chunk_size: events per chunk of the construction pass, which holds one chunk and its
            temporaries at a time (some 60 bytes an event).

    Raises:
        ConfigError: not exactly one of ``window_ms`` and ``events_per_window``, a window or stride
            that is not positive, a stride of the other kind of window, a ``cache_dir`` that is not a
            directory, or a bad ``chunk_size``.
        ReaderError: the file is missing, unknown or unreadable; with ``labelled``, its format holds no
            labels, the label field is missing or not integer, or labels or flags do not match the
            events one to one.
        EventFormatError: the events are invalid, e.g. out of order or outside ``sensor_size``.

    Examples:
        >>> from evseg_torch.synthetic import make_scene
        >>> folder = tempfile.TemporaryDirectory()
        >>> path = Path(folder.name) / "scene.npy"
        >>> np.save(path, make_scene((90, 120), 0.03, n_objects=1, rng=0).events)
        >>> dataset = EventWindowDataset(path, window_ms=10, sensor_size=(90, 120))
        >>> item = dataset[1]
        >>> len(dataset), item["t_start_us"] - dataset[0]["t_start_us"], item["events"].t.dtype
        (3, 10000, torch.float32)
        >>> folder.cleanup()
    """

    def __init__(
        self,
        path: str | Path,
        *,
        window_ms: float | None = None,
        stride_ms: float | None = None,
        events_per_window: int | None = None,
        stride_events: int | None = None,
        sensor_size: tuple[int, int] | None = None,
        labelled: bool = False,
        label_field: str = "label",
        ignore_field: str | None = "ambiguous",
        cache_dir: str | Path | None = None,
        chunk_size: int = 100_000,
    ) -> None:
        self._window_us, self._stride_us, self._count, self._stride_count = _geometry(
            window_ms, stride_ms, events_per_window, stride_events
        )
        self.path = existing_file(path)
        self.labelled = bool(labelled)
        size = resolve_sensor_size(self.path, sensor_size)
        labels = _open_labels(self.path, label_field, ignore_field) if self.labelled else None
        in_place = _canonical_npy(self.path)
        self._directory = None
        if cache_dir is not None and not Path(cache_dir).is_dir():
            raise ConfigError(f"cache_dir must be an existing directory, got {str(cache_dir)!r}")
        if in_place is None or labels is not None:
            self._directory = Path(tempfile.mkdtemp(prefix="evseg-windows-", dir=cache_dir))
            # Only the creating process removes the cache: forked DataLoader workers hold copies.
            self._finalizer = weakref.finalize(self, _remove_cache, self._directory, os.getpid())
        try:
            with _Cache(self._directory, labels, write_events=in_place is None) as cache:
                self._time_origin_us, self._ranges, self.n_events, inferred = self._pass(
                    iter_event_chunks(self.path, chunk_size, sensor_size=size), cache, labels
                )
        except BaseException:
            if self._directory is not None:
                self._finalizer()
            raise
        events, self._labels, self._ignore = cache.rows
        self._events = events if events is not None else in_place
        self.sensor_size = size or inferred

    @property
    def windows(self) -> np.ndarray:
        """``[begin, end)`` event indices of every window, int64 :math:`(M, 2)` (a copy)."""
        return self._ranges.copy()

    def __len__(self) -> int:
        return len(self._ranges)

    def __getitem__(self, index: int) -> dict:
        """The window ``index`` (negative counts from the end) as a dict (see the module docstring)."""
        index = operator.index(index)
        if not -len(self) <= index < len(self):
            raise IndexError(f"window {index} is out of range for {len(self)} windows")
        index %= len(self)
        begin, end = (int(v) for v in self._ranges[index])
        events = self._events.read(begin, end)
        if self._window_us is not None:
            t_start = self._time_origin_us + index * self._stride_us
        else:
            t_start = int(events["t"][0])
        item = {"events": to_torch(events, t_ref_us=t_start)}
        if self.labelled:
            item["labels"] = torch.from_numpy(self._labels.read(begin, end))
            item["ignore"] = torch.from_numpy(self._ignore.read(begin, end))
        return item | {"t_start_us": t_start, "index": index, "sensor_size": self.sensor_size}

    def __getstate__(self) -> dict:
        # A copy sent to a spawned worker reads the cache but does not own it.
        return {key: value for key, value in self.__dict__.items() if key != "_finalizer"}

    def __repr__(self) -> str:
        if self._window_us is not None:
            geometry = f"window_ms={self._window_us / 1000}, stride_ms={self._stride_us / 1000}"
        else:
            geometry = f"events_per_window={self._count}, stride_events={self._stride_count}"
        return (
            f"{type(self).__name__}({str(self.path)!r}, {geometry}, windows={len(self)}, "
            f"events={self.n_events}, sensor_size={self.sensor_size}, labelled={self.labelled})"
        )

    def _pass(self, chunks, cache: _Cache, labels: _Labels | None):
        """Write the cache and index the windows in one pass; returns what the items need."""
        by_time = self._window_us is not None
        if by_time:
            index = TimeWindowIndex(self._window_us, self._stride_us)
        else:
            index = CountWindowIndex(self._count, self._stride_count)
        ranges, n_events, max_y, max_x = [], 0, 0, 0
        for chunk in chunks:
            end = n_events + len(chunk)
            cache.append(chunk, labels.read(n_events, end) if labels is not None else None)
            ranges.append(index.add(chunk["t"] if by_time else len(chunk)))
            n_events = end
            max_y, max_x = max(max_y, int(chunk["y"].max())), max(max_x, int(chunk["x"].max()))
        if labels is not None and n_events != labels.length:
            # Labels past the events' end were never read; short ones were read short, never padded.
            raise ReaderError(
                f"{self.path}: {labels.label_field!r} holds {labels.length} labels for {n_events} events; "
                "labels must match the events one to one"
            )
        ranges = np.concatenate([*ranges, index.finish()])
        origin_us = index.start_us if by_time else None
        return origin_us, ranges, n_events, (max_y + 1, max_x + 1)


class _Rows(NamedTuple):
    """A 1-D array in a ``.npy`` file, whose rows are read with plain file reads."""

    path: Path
    dtype: np.dtype
    offset: int

    def read(self, begin: int, end: int) -> np.ndarray:
        """Rows ``[begin, end)`` as a new, writable array."""
        return np.fromfile(
            self.path, dtype=self.dtype, count=end - begin, offset=self.offset + begin * self.dtype.itemsize
        )


class _NpyWriter:
    """Appends to a 1-D ``.npy`` file with plain writes; a memory map's dirty pages would stay resident.

    The header is written first for length 0 and rewritten with the final length at the end: NumPy
    pads every header so that any length fits in place, for exactly this kind of growth.
    """

    def __init__(self, path: Path, dtype) -> None:
        self.path, self.dtype, self.length = path, np.dtype(dtype), 0
        self._file = open(path, "wb")  # appended to chunk by chunk, closed by finish() or discard()
        self._header()
        self.offset = self._file.tell()

    def append(self, values: np.ndarray) -> None:
        np.ascontiguousarray(values, dtype=self.dtype).tofile(self._file)
        self.length += len(values)

    def finish(self) -> _Rows:
        """Write the final length into the header, close the file and return its rows."""
        self._file.seek(0)
        self._header()
        self._file.close()
        return _Rows(self.path, self.dtype, self.offset)

    def discard(self) -> None:
        self._file.close()

    def _header(self) -> None:
        descr = np.lib.format.dtype_to_descr(self.dtype)
        np.lib.format.write_array_header_1_0(
            self._file, {"descr": descr, "fortran_order": False, "shape": (self.length,)}
        )


class _Cache:
    """The cache files written during the pass: events (unless read in place), labels and flags.

    A context manager: on a clean exit ``rows`` holds the rows of each file (``None`` for one not
    written); on an error every file is closed unfinished.
    """

    def __init__(self, directory: Path | None, labels: _Labels | None, write_events: bool) -> None:
        self._events = _NpyWriter(directory / "events.npy", EVENT_DTYPE) if write_events else None
        self._labels = _NpyWriter(directory / "labels.npy", np.int64) if labels is not None else None
        self._ignore = _NpyWriter(directory / "ignore.npy", np.bool_) if labels is not None else None
        self.rows = (None, None, None)

    def __enter__(self) -> _Cache:
        return self

    def __exit__(self, error_type, error, traceback) -> None:
        writers = (self._events, self._labels, self._ignore)
        if error_type is None:
            self.rows = tuple(writer.finish() if writer is not None else None for writer in writers)
        else:
            for writer in writers:
                if writer is not None:
                    writer.discard()

    def append(self, events: np.ndarray, labels: tuple[np.ndarray, np.ndarray] | None) -> None:
        if self._events is not None:
            self._events.append(events)
        if labels is not None:
            self._labels.append(labels[0])
            self._ignore.append(labels[1])


class _Labels:
    """Per-event labels and ignore flags of a labelled file, read by event ranges.

    ``.npz`` members are loaded whole (zip members cannot be read in part; the event columns are loaded
    whole too); structured ``.npy`` fields are read row range by row range from the file.
    """

    def __init__(self, path: Path, label_field: str, ignore_field: str | None) -> None:
        self.label_field = label_field
        if path.suffix.lower() == ".npz":
            self._arrays, self._rows = _npz_members(path, label_field, ignore_field), None
            self.length, names = len(self._arrays[label_field]), tuple(self._arrays)
            label_dtype = self._arrays[label_field].dtype
        else:
            self._arrays, (self._rows, self.length) = None, _npy_rows(path, label_field)
            names, label_dtype = self._rows.dtype.names, self._rows.dtype[label_field]
        if not np.issubdtype(label_dtype, np.integer):
            raise ReaderError(f"{path}: {label_field!r} must hold integer labels, got dtype {label_dtype}")
        self._ignore_field = ignore_field if ignore_field in names else None

    def read(self, begin: int, end: int) -> tuple[np.ndarray, np.ndarray]:
        """Labels int64 and flags bool of events ``[begin, end)`` (fewer past the file's labels)."""
        if self._rows is not None:
            values = self._rows.read(begin, end)
        else:
            values = {name: array[begin:end] for name, array in self._arrays.items()}
        labels = values[self.label_field].astype(np.int64)
        if self._ignore_field is None:
            return labels, np.zeros(len(labels), dtype=bool)
        return labels, values[self._ignore_field].astype(bool)


def _open_labels(path: Path, label_field: str, ignore_field: str | None) -> _Labels:
    if path.suffix.lower() not in (".npz", ".npy"):
        raise ReaderError(
            f"{path}: per-event labels are read from .npz members or structured .npy fields; "
            f"{path.suffix!r} files hold none"
        )
    return _Labels(path, label_field, ignore_field)


def _npz_members(path: Path, label_field: str, ignore_field: str | None) -> dict[str, np.ndarray]:
    with reading(path, WHAT_NPZ), open_npz(path) as npz:
        if label_field not in npz.files:
            raise ReaderError(f"no per-event label field {label_field!r} (members: {', '.join(npz.files)})")
        arrays = {name: npz[name] for name in (label_field, ignore_field) if name in npz.files}
    lengths = {name: array.shape for name, array in arrays.items()}
    if any(array.ndim != 1 for array in arrays.values()) or len(set(lengths.values())) != 1:
        raise ReaderError(f"{path}: labels and ignore flags must be 1-D of one length, got shapes {lengths}")
    return arrays


def _npy_rows(path: Path, label_field: str) -> tuple[_Rows, int]:
    with reading(path, WHAT_NPY), open(path, "rb") as file:
        shape, dtype = _npy_header(file)
        offset = file.tell()
    names = dtype.names or ()
    if label_field not in names or len(shape) != 1:
        raise ReaderError(
            f"{path}: no per-event label field {label_field!r}; labels need a 1-D structured .npy "
            f"(dtype {dtype}, shape {shape})"
        )
    return _Rows(path, dtype, offset), int(shape[0])


def _npy_header(file) -> tuple[tuple[int, ...], np.dtype]:
    version = np.lib.format.read_magic(file)
    read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    shape, fortran_order, dtype = read(file)
    if fortran_order and len(shape) > 1:
        raise ReaderError(f"Fortran-ordered arrays of shape {shape} are not event files")
    return shape, dtype


def _canonical_npy(path: Path) -> _Rows | None:
    """The rows of a 1-D ``.npy`` of exactly :data:`EVENT_DTYPE`, or ``None`` for any other file."""
    if path.suffix.lower() != ".npy":
        return None
    try:
        with open(path, "rb") as file:
            shape, dtype = _npy_header(file)
            offset = file.tell()
    except (OSError, ValueError):
        return None  # the construction pass reports what is wrong with the file
    return _Rows(path, dtype, offset) if dtype == EVENT_DTYPE and len(shape) == 1 else None


def _geometry(window_ms, stride_ms, events_per_window, stride_events) -> tuple:
    """``(window_us, stride_us, events, stride_events)``; the two of the other kind are ``None``."""
    if (window_ms is None) == (events_per_window is None):
        raise ConfigError(
            "give exactly one of window_ms and events_per_window, "
            f"got {window_ms!r} and {events_per_window!r}"
        )
    if window_ms is not None:
        if stride_events is not None:
            raise ConfigError("stride_events applies to events_per_window; time windows step by stride_ms")
        window_us = _microseconds(window_ms, "window_ms")
        stride_us = window_us if stride_ms is None else _microseconds(stride_ms, "stride_ms")
        return window_us, stride_us, None, None
    if stride_ms is not None:
        raise ConfigError("stride_ms applies to window_ms; windows of an event count step by stride_events")
    count = check_integer(events_per_window, "events_per_window", at_least=1)
    stride = count if stride_events is None else check_integer(stride_events, "stride_events", at_least=1)
    return None, None, count, stride


def _microseconds(milliseconds, name: str) -> int:
    """Whole microseconds, rounded as :func:`~evseg_torch.events.iter_windows` rounds them."""
    try:
        value = round(float(milliseconds) * 1000)
    except (TypeError, ValueError, OverflowError):
        raise ConfigError(f"{name} must be a positive number of milliseconds, got {milliseconds!r}") from None
    if value <= 0:
        raise ConfigError(f"{name} must be positive (at least 1 us), got {milliseconds!r}")
    return value


def _remove_cache(directory: Path, owner_pid: int) -> None:
    if os.getpid() == owner_pid:
        shutil.rmtree(directory, ignore_errors=True)

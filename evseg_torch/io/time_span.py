"""The first and last timestamps of an event file, where finding them costs no pass over the events.

Progress bars use it for their totals: array files (``.npy``, ``.npz``, HDF5) are read at both ends, a
text file's last line is found from its end (an rpg / ECD / EED folder's ``events.txt`` too), an EVIMO2v2
folder's time file is read at both ends. Other formats give ``None``, as does any file these reads
fail on (the reading pass itself reports what is wrong).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from evseg_torch.errors import EvsegError
from evseg_torch.events import as_events
from evseg_torch.io import evimo2, numpy_files, rpg_folder, text

_TAIL_BYTES = 1 << 16


def read_time_span(path) -> tuple[int, int] | None:
    """``(first, last)`` timestamps in µs of the events of ``path``, or ``None`` where not cheap.

    Examples:
        >>> read_time_span("events.npy")  # doctest: +SKIP
        (0, 8000000)
    """
    path = Path(path)
    if path.is_dir():  # the folder layouts of io.dispatch, in its order
        if evimo2.is_sequence(path):
            ends = _evimo2
        elif (path / "metadata.yaml").is_file():  # a ROS 2 bag
            return None
        elif rpg_folder.is_sequence(path):
            path, ends = path / rpg_folder.EVENTS, _text
        else:
            return None
    else:
        ends = _ENDS.get(path.suffix.lower())
    if ends is None:
        return None
    try:
        rows = ends(path)
        if rows is None or len(rows) < 2:
            return None
        t = as_events(rows)["t"]
    except (EvsegError, OSError, ValueError, KeyError, IndexError):
        return None
    return int(t[0]), int(t[-1])


def _evimo2(folder: Path) -> np.ndarray:
    t, xy, p = evimo2._event_columns(folder)
    ends = np.array([0, -1])
    return evimo2._rows(t[ends], xy[ends], p[ends], flip=False)


def _npy(path: Path) -> np.ndarray:
    data = numpy_files.read_npy(path)
    return np.array(data[[0, -1]])


def _npz(path: Path) -> np.ndarray:
    with numpy_files.open_npz(path) as npz:
        columns = numpy_files._columns(npz)
    return numpy_files._assemble(columns, np.array([0, -1]))


def _hdf5(path: Path) -> np.ndarray:
    import h5py

    from evseg_torch.io import hdf5

    with h5py.File(path, "r") as file:
        names, count = hdf5._layout(file)
        return np.concatenate([hdf5._rows(file, names, 0, 1), hdf5._rows(file, names, count - 1, count)])


def _text(path: Path) -> np.ndarray | None:
    first = next(text.chunks(path, 1000), None)
    with open(path, "rb") as file:
        file.seek(max(file.seek(0, os.SEEK_END) - _TAIL_BYTES, 0))
        tail = file.read().splitlines()[1:]  # the first may be cut
    last = text._parse(tail, first_line=1) if tail else None
    if first is None or last is None or not len(last):
        return None
    return np.stack([first[0], last[-1]])


_ENDS = {".npy": _npy, ".npz": _npz, ".h5": _hdf5, ".hdf5": _hdf5, ".txt": _text}

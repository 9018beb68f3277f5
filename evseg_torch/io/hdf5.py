"""Reader of HDF5 event files (``.h5``/``.hdf5``) through h5py, in two layouts.

=============  ==============================================  ==========================================
layout         datasets                                        time
=============  ==============================================  ==========================================
event_utils    ``events/xs``, ``ys``, ``ts``, ``ps`` (bool or  ``ts`` float seconds
               int), root attribute ``sensor_resolution``
DSEC           ``events/x``, ``y``, ``t``, ``p``; optional     ``t`` integer µs, plus root ``t_offset``
               ``t_offset`` (µs) and ``ms_to_idx``             (µs, 0 when absent)
=============  ==============================================  ==========================================

``sensor_resolution`` is read as ``(H, W)``, as event_utils (Stoffregen et al.) writes and reads it;
DSEC files store no sensor size (640 x 480). Datasets are sliced, so chunks stream from disk.
``hdf5plugin`` is imported when installed so that Blosc-compressed DSEC files open.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np

from evseg_torch.errors import ReaderError

with contextlib.suppress(ImportError):
    import hdf5plugin  # noqa: F401  (registers the Blosc/Zstd filters that DSEC files use)


_EVENT_UTILS = ("xs", "ys", "ts", "ps")
_DSEC = ("x", "y", "t", "p")
_LAYOUTS_HELP = "expected datasets events/{xs,ys,ts,ps} (event_utils) or events/{x,y,t,p} (DSEC)"


def read(path: Path) -> np.ndarray:
    """All events, as :math:`(N, 4)` seconds (event_utils) or a structured array in µs (DSEC)."""
    with h5py.File(path, "r") as file:
        names, count = _layout(file)
        return _rows(file, names, 0, count)


def chunks(path: Path, chunk_size: int) -> Iterator[np.ndarray]:
    """Consecutive slices of at most ``chunk_size`` events."""
    with h5py.File(path, "r") as file:
        names, count = _layout(file)
        for begin in range(0, count, chunk_size):
            yield _rows(file, names, begin, min(begin + chunk_size, count))


def ends(path: Path) -> np.ndarray:
    """The first and the last event."""
    with h5py.File(path, "r") as file:
        names, count = _layout(file)
        return np.concatenate([_rows(file, names, 0, 1), _rows(file, names, count - 1, count)])


def sensor_size(path: Path) -> tuple[int, int] | None:
    """``(H, W)`` from the root attribute ``sensor_resolution``, else ``None``."""
    with h5py.File(path, "r") as file:
        resolution = file.attrs.get("sensor_resolution")
    if resolution is None:
        return None
    height, width = np.asarray(resolution).ravel()[:2]
    return int(height), int(width)


def _layout(file: h5py.File) -> tuple[tuple[str, ...], int]:
    group = file.get("events")
    if not isinstance(group, h5py.Group):
        raise ReaderError(f"no 'events' group; {_LAYOUTS_HELP}")
    names = next((names for names in (_EVENT_UTILS, _DSEC) if all(name in group for name in names)), None)
    if names is None:
        raise ReaderError(f"the 'events' group holds {sorted(group)}; {_LAYOUTS_HELP}")
    shapes = {name: group[name].shape for name in names}
    if len(set(shapes.values())) != 1 or len(shapes[names[0]]) != 1:
        raise ReaderError(f"event datasets must be 1-D and of one length, got shapes {shapes}")
    time = group[names[2]]
    if names == _EVENT_UTILS and time.dtype.kind != "f":
        raise ReaderError(f"events/ts must hold float seconds (event_utils layout), got dtype {time.dtype}")
    if names == _DSEC and time.dtype.kind not in "iu":
        raise ReaderError(f"events/t must hold integer microseconds (DSEC layout), got dtype {time.dtype}")
    return names, shapes[names[0]][0]


def _rows(file: h5py.File, names: tuple[str, ...], begin: int, end: int) -> np.ndarray:
    group = file["events"]
    x, y, t, p = (group[name][begin:end] for name in names)
    if names == _EVENT_UTILS:
        return np.column_stack([t, x, y, p]).astype(np.float64)
    offset = int(file["t_offset"][()]) if "t_offset" in file else 0
    out = np.empty(end - begin, dtype=[("t", np.int64), ("x", x.dtype), ("y", y.dtype), ("p", p.dtype)])
    out["t"] = t.astype(np.int64) + offset
    out["x"], out["y"], out["p"] = x, y, p
    return out

"""EVIMO2 (Burner et al., 2022) sequences in the v2 "npz" layout: one folder per camera and sequence.

===========================  ===================================================================
file                         content
===========================  ===================================================================
``dataset_events_t.npy``     event times :math:`(N,)`, float seconds
``dataset_events_xy.npy``    ``[x, y]`` :math:`(N, 2)`, x the column
``dataset_events_p.npy``     polarity :math:`(N,)`, 0/1
``dataset_info.npz``         ``K`` :math:`(3, 3)`, ``D`` :math:`(4,)` and ``meta``, a pickled dict:
                             ``meta["frames"]``, each with ``id`` and ``ts`` (seconds, the events'
                             time base), and ``meta["meta"]``, the camera, with ``res_x``, ``res_y``
``dataset_mask.npz``         one ``mask_{id:010d}`` image :math:`(H, W)` per frame, the object id of
                             each pixel, 0 where no object
===========================  ===================================================================

The depth and grey-frame files of the layout are not read. Events are read from the three ``.npy``
files (memory-mapped, then read block by block when streaming, as :mod:`.numpy_files` does), with
no unpickling; the sensor size is the masks' image size, read from the mask file's headers. The mask
times live only in the pickled ``meta``, so :func:`load_evimo2` (events and ground truth) needs
``trusted=True``, like :func:`~evseg_torch.io.evimo.load_evimo`.

Polarity: EVIMO2 stores the ``samsung_mono`` camera's polarity inverted relative to its Prophesee
cameras (``left_camera``, ``right_camera``). By default the polarity of a folder whose path holds a
``samsung_mono`` component (the dataset's own ``samsung_mono/<category>/<split>/<sequence>`` tree) is
flipped, so ON means brighter for every camera; ``flip_polarity`` overrides that guess either way.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from evseg_torch.errors import ReaderError
from evseg_torch.events import as_events, check_sensor_size
from evseg_torch.io.evimo import EvimoSequence
from evseg_torch.io.guard import reading
from evseg_torch.io.numpy_files import member_shape, npy_row_blocks, open_npz

WHAT = "EVIMO2v2 sequence folder"

EVENT_FILES = ("dataset_events_t.npy", "dataset_events_xy.npy", "dataset_events_p.npy")
INFO_FILE, MASK_FILE = "dataset_info.npz", "dataset_mask.npz"
INVERTED_POLARITY_CAMERAS = ("samsung_mono",)


def is_sequence(folder: Path) -> bool:
    """Whether a folder holds the three event files of the layout."""
    return all((folder / name).is_file() for name in EVENT_FILES)


def polarity_inverted(folder: Path) -> bool:
    """Whether the folder's path names a camera whose polarity EVIMO2 stores inverted."""
    return any(part in INVERTED_POLARITY_CAMERAS for part in Path(folder).resolve().parts)


def read(folder: Path, flip_polarity: bool | None = None) -> np.ndarray:
    """All events, as float64 :math:`(N, 4)` rows ``[t_seconds, x, y, p]``."""
    t, xy, p = _event_columns(folder)
    return _rows(t, xy, p, _flip(folder, flip_polarity))


def chunks(folder: Path, chunk_size: int, flip_polarity: bool | None = None) -> Iterator[np.ndarray]:
    """Consecutive blocks of at most ``chunk_size`` events, each read from the three files on its own."""
    columns = _event_columns(folder)
    flip = _flip(folder, flip_polarity)
    blocks = [
        npy_row_blocks(folder / name, data, chunk_size)
        for name, data in zip(EVENT_FILES, columns, strict=True)
    ]
    for t, xy, p in zip(*blocks, strict=True):
        yield _rows(t, xy, p, flip)


def ends(folder: Path, flip_polarity: bool | None = None) -> np.ndarray:
    """The first and the last event, read from the memory-mapped files."""
    t, xy, p = _event_columns(folder)
    rows = np.array([0, -1])
    return _rows(t[rows], xy[rows], p[rows], _flip(folder, flip_polarity))


def sensor_size(folder: Path) -> tuple[int, int] | None:
    """``(H, W)`` of the first mask, read from its header; ``None`` without a mask file or masks."""
    if not (folder / MASK_FILE).is_file():
        return None
    with reading(folder / MASK_FILE, "EVIMO2 mask file"), open_npz(folder / MASK_FILE) as npz:
        names = sorted(name for name in npz.files if name.startswith("mask_"))
        if not names:
            return None
        shape = member_shape(npz, names[0])
    if len(shape) != 2:
        raise ReaderError(f"{folder / MASK_FILE}: masks must be (H, W) images, got shape {shape}")
    return int(shape[0]), int(shape[1])


def load_evimo2(folder, trusted: bool = False, flip_polarity: bool | None = None) -> EvimoSequence:
    """Read an EVIMO2v2 sequence folder: events, per-frame object masks and calibration.

    Args:
        folder: the sequence's folder (module doc).
        trusted: allow unpickling ``dataset_info.npz``'s ``meta``, which holds the mask times.
            Unpickling can run arbitrary code: pass ``True`` only for files from a source you trust.
        flip_polarity: invert the polarity; ``None`` (default) inverts it for ``samsung_mono`` folders.

    Returns:
        An :class:`~evseg_torch.io.EvimoSequence` (as the EV-IMO 1 loader returns), so that
        :func:`~evseg_torch.evaluation.evimo.evaluate_evimo` scores it; ``masks`` hold the object
        ids as stored, ``sensor_size`` is ``(res_y, res_x)``.

    Raises:
        ReaderError: ``trusted`` is false; a file is missing or corrupt; ``meta`` lacks the frames or
            the resolution; a frame's mask is missing or not of the resolution.
        EventFormatError: the events are invalid (e.g. timestamps decrease, or outside the sensor).
    """
    folder = _sequence_folder(folder)
    info_path, mask_path = folder / INFO_FILE, folder / MASK_FILE
    for path in (info_path, mask_path):
        if not path.is_file():
            raise ReaderError(f"{folder}: no {path.name}; the ground truth of an EVIMO2v2 sequence needs it")
    with reading(info_path, "EVIMO2 info file"), open_npz(info_path, allow_pickle=bool(trusted)) as npz:
        missing = [key for key in ("K", "D", "meta") if key not in npz.files]
        if missing:
            raise ReaderError(f"missing key(s) {missing}; it holds {sorted(npz.files)}")
        if not trusted:
            raise ReaderError(
                "the mask times come from 'meta', a pickled dict; pass trusted=True to unpickle it "
                "(only for files from a trusted source: unpickling can run code)"
            )
        frame_ids, times_s, size = _frames(npz["meta"])
        K, D = np.array(npz["K"], dtype=np.float64), np.array(npz["D"], dtype=np.float64).ravel()
    if K.shape != (3, 3) or D.shape != (4,):
        raise ReaderError(f"{info_path}: K must be (3, 3) and D (4,), got {K.shape} and {D.shape}")
    with reading(mask_path, "EVIMO2 mask file"), open_npz(mask_path) as npz:
        masks = _masks(npz, frame_ids, size)
    with reading(folder, WHAT):
        events = as_events(read(folder, flip_polarity), size)
    return EvimoSequence(events=events, masks=masks, mask_times_s=times_s, K=K, D=D, sensor_size=size)


def _sequence_folder(folder) -> Path:
    folder = Path(folder)
    if not folder.is_dir():
        raise ReaderError(f"{folder}: not a folder; an EVIMO2v2 sequence is a folder of .npy/.npz files")
    if not is_sequence(folder):
        missing = [name for name in EVENT_FILES if not (folder / name).is_file()]
        raise ReaderError(f"{folder}: not an EVIMO2v2 sequence folder: no {', '.join(missing)}")
    return folder


def _event_columns(folder: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t, xy, p = (np.load(folder / name, mmap_mode="r", allow_pickle=False) for name in EVENT_FILES)
    if t.ndim != 1 or p.shape != t.shape or xy.shape != (len(t), 2):
        raise ReaderError(
            f"event files must be t (N,), xy (N, 2) and p (N,) for one N, "
            f"got {t.shape}, {xy.shape}, {p.shape}"
        )
    return t, xy, p


def _flip(folder: Path, flip_polarity: bool | None) -> bool:
    return polarity_inverted(folder) if flip_polarity is None else bool(flip_polarity)


def _rows(t: np.ndarray, xy: np.ndarray, p: np.ndarray, flip: bool) -> np.ndarray:
    p = np.asarray(p)
    polarity = (p <= 0) if flip else (p > 0)
    return np.column_stack([t, xy[:, 0], xy[:, 1], polarity]).astype(np.float64)


def _frames(meta: np.ndarray) -> tuple[list[int], np.ndarray, tuple[int, int]]:
    meta = meta.item() if meta.dtype == object and meta.ndim == 0 else meta
    frames = meta.get("frames") if isinstance(meta, dict) else None
    camera = meta.get("meta") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not all(
        isinstance(frame, dict) and "ts" in frame and "id" in frame for frame in frames
    ):
        raise ReaderError("'meta' must be a dict whose 'frames' is a list of dicts with 'id' and 'ts'")
    if not isinstance(camera, dict) or "res_x" not in camera or "res_y" not in camera:
        raise ReaderError("'meta' must hold the camera's 'meta' dict with 'res_x' and 'res_y'")
    size = check_sensor_size((camera["res_y"], camera["res_x"]))
    ids = [int(frame["id"]) for frame in frames]
    return ids, np.array([float(frame["ts"]) for frame in frames], dtype=np.float64), size


def _masks(npz, frame_ids: list[int], size: tuple[int, int]) -> np.ndarray:
    names = [f"mask_{frame_id:010d}" for frame_id in frame_ids]
    missing = [name for name in names if name not in npz.files]
    if missing:
        raise ReaderError(f"{len(missing)} of {len(names)} frames have no mask, the first {missing[0]!r}")
    masks = np.zeros((len(names), *size), dtype=np.uint16)
    for index, name in enumerate(names):
        mask = npz[name]
        if mask.shape != size or mask.dtype.kind not in "iub":
            raise ReaderError(f"{name} must be an integer {size} (H, W) image, got {mask.dtype} {mask.shape}")
        masks[index] = mask
    return masks

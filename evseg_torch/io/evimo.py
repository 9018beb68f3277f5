"""EV-IMO (Mitrokhin et al., IROS 2019) sequences in the original single-``.npz`` layout, and a writer.

The layout, as written by pydvs' ``evimo-gen.py``:

===================  ==========================================================================
key                  content
===================  ==========================================================================
``events``           float :math:`(N, 4)` rows ``[t, x, y, p]``, ``t`` seconds, ``p`` 0/1
``mask``             uint16 :math:`(F, H, W)`, object id * 1000 per pixel, 0 where no object
``meta``             a pickled dict; ``meta["frames"][i]["ts"]`` is the time of ``mask[i]``
                     (seconds, the events' time base), ``meta["meta"]`` holds resolution and
                     intrinsics
``K``, ``D``         camera matrix :math:`(3, 3)` and distortion :math:`(4,)`
``index``            first event at or after each multiple of ``discretization`` seconds
``discretization``   the spacing of ``index`` in seconds
===================  ==========================================================================

The original files also hold ``depth`` and ``classical`` (grey frames); they are not read. The mask
times live only in the pickled ``meta``, and unpickling a file can run arbitrary code, so
:func:`load_evimo` needs ``trusted=True``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evseg_torch.errors import ReaderError, ShapeError
from evseg_torch.events import as_events, check_sensor_size
from evseg_torch.io.guard import existing_file, reading
from evseg_torch.io.numpy_files import open_npz

WHAT = "EV-IMO npz file"

_ID_SCALE = 1000
_MAX_OBJECT_ID = np.iinfo(np.uint16).max // _ID_SCALE
_REQUIRED_KEYS = ("events", "mask", "meta", "K", "D")


@dataclass(frozen=True, eq=False)
class EvimoSequence:
    """One EV-IMO sequence: events, per-frame object masks and calibration.

    Attributes:
        events: canonical events :math:`(N,)` (see :func:`~evseg_torch.events.as_events`), ``t`` in
            µs of the sequence's time base.
        masks: object ids :math:`(F, H, W)` uint16, 0 where no object (the file's values / 1000).
        mask_times_s: time of each mask in seconds, same time base as ``events``, :math:`(F,)`.
        K: camera matrix :math:`(3, 3)`.
        D: distortion coefficients (radtan or equidistant, as the sequence was calibrated) :math:`(4,)`.
        sensor_size: ``(H, W)``, the masks' image size.
    """

    events: np.ndarray
    masks: np.ndarray
    mask_times_s: np.ndarray
    K: np.ndarray
    D: np.ndarray
    sensor_size: tuple[int, int]


def load_evimo(path, trusted: bool = False) -> EvimoSequence:
    """Read an EV-IMO sequence ``.npz``.

    Args:
        path: the ``.npz`` file.
        trusted: allow unpickling ``meta``, which holds the mask timestamps. Unpickling can run
            arbitrary code: pass ``True`` only for files from a source you trust.

    Returns:
        The sequence; events are checked against the masks' ``(H, W)``.

    Raises:
        ReaderError: ``trusted`` is false, the file is missing, corrupt, lacks a key, or ``meta``
            does not match ``mask``.
        EventFormatError: the events are invalid (e.g. timestamps decrease, or outside the masks).
    """
    path = existing_file(path)
    with reading(path, WHAT), open_npz(path, allow_pickle=bool(trusted)) as npz:
        missing = [key for key in _REQUIRED_KEYS if key not in npz.files]
        if missing:
            raise ReaderError(f"not an EV-IMO npz: missing key(s) {missing}; it holds {sorted(npz.files)}")
        if not trusted:
            raise ReaderError(
                "the mask timestamps come from 'meta', a pickled dict; pass trusted=True to unpickle it "
                "(only for files from a trusted source: unpickling can run code)"
            )
        raw_masks = npz["mask"]
        if raw_masks.ndim != 3:
            raise ReaderError(f"'mask' must be (F, H, W), got shape {raw_masks.shape}")
        mask_times_s = _mask_times(npz["meta"], len(raw_masks))
        sensor_size = (int(raw_masks.shape[1]), int(raw_masks.shape[2]))
        return EvimoSequence(
            events=as_events(npz["events"], sensor_size),
            masks=_object_ids(raw_masks),
            mask_times_s=mask_times_s,
            K=np.array(npz["K"], dtype=np.float64),
            D=np.array(npz["D"], dtype=np.float64),
            sensor_size=sensor_size,
        )


def save_evimo(
    path,
    events,
    masks: np.ndarray,
    mask_times_s: np.ndarray,
    *,
    K: np.ndarray | None = None,
    D: np.ndarray | None = None,
    discretization: float = 0.01,
) -> Path:
    """Write a sequence in the EV-IMO ``.npz`` layout (e.g. from synthetic data, for tests).

    Args:
        path: the file to write, exactly as named.
        events: anything :func:`~evseg_torch.events.as_events` accepts; written as float64 rows
            ``[t_seconds, x, y, p]`` with ``p`` in {0, 1}.
        masks: object ids :math:`(F, H, W)`, non-negative integers up to 65 (stored as id * 1000 in
            uint16), 0 where no object.
        mask_times_s: time of each mask in seconds, events' time base, :math:`(F,)`.
        K: camera matrix :math:`(3, 3)`; defaults to a placeholder with focal length ``max(H, W)``
            and the principal point at the image centre.
        D: distortion :math:`(4,)`; defaults to zeros.
        discretization: spacing in seconds of the written ``index``.

    Returns:
        The path written.

    Raises:
        ShapeError: the masks, times or calibration have the wrong shape or values.
        EventFormatError: the events are invalid or lie outside the masks' ``(H, W)``.
    """
    masks = np.asarray(masks)
    times = np.asarray(mask_times_s, dtype=np.float64)
    if masks.ndim != 3 or times.shape != (masks.shape[0],):
        raise ShapeError(f"masks must be (F, H, W) and mask_times_s (F,), got {masks.shape}, {times.shape}")
    if masks.dtype.kind not in "iub" or masks.min(initial=0) < 0 or masks.max(initial=0) > _MAX_OBJECT_ID:
        raise ShapeError(f"masks must hold integer object ids in [0, {_MAX_OBJECT_ID}]")
    height, width = check_sensor_size(masks.shape[1:])
    canonical = as_events(events, (height, width))
    K = _default_camera(height, width) if K is None else np.array(K, dtype=np.float64)
    D = np.zeros(4) if D is None else np.array(D, dtype=np.float64)
    if K.shape != (3, 3) or D.shape != (4,):
        raise ShapeError(f"K must be (3, 3) and D (4,), got {K.shape} and {D.shape}")
    t_s = canonical["t"] * 1e-6
    rows = np.column_stack([t_s, canonical["x"], canonical["y"], canonical["p"] > 0]).astype(np.float64)
    steps = np.arange(int(np.floor((t_s[-1] - t_s[0]) / discretization)) + 1)
    meta = {
        "meta": {"res_x": width, "res_y": height, "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
        | {f"k{i + 1}": float(value) for i, value in enumerate(D)},
        "frames": [{"id": i, "ts": float(t)} for i, t in enumerate(times)],
    }
    path = Path(path)
    with open(path, "wb") as file:
        np.savez_compressed(
            file,
            events=rows,
            mask=masks.astype(np.uint16) * np.uint16(_ID_SCALE),
            meta=np.array(meta, dtype=object),
            K=K,
            D=D,
            index=np.searchsorted(t_s, t_s[0] + steps * discretization).astype(np.uint32),
            discretization=np.float64(discretization),
        )
    return path


def _default_camera(height: int, width: int) -> np.ndarray:
    focal = float(max(height, width))
    return np.array([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]])


def _mask_times(meta: np.ndarray, count: int) -> np.ndarray:
    meta = meta.item() if meta.dtype == object and meta.ndim == 0 else meta
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not all(isinstance(frame, dict) and "ts" in frame for frame in frames):
        raise ReaderError("'meta' must be a dict whose 'frames' is a list of dicts with 'ts'")
    if len(frames) != count:
        raise ReaderError(f"'meta' lists {len(frames)} frames but 'mask' holds {count}")
    return np.array([float(frame["ts"]) for frame in frames], dtype=np.float64)


def _object_ids(raw_masks: np.ndarray) -> np.ndarray:
    """File values are id * 1000; round to the nearest id, in uint16 so no big temporary is made."""
    raw = raw_masks.astype(np.uint16, copy=False)
    return raw // _ID_SCALE + (raw % _ID_SCALE >= _ID_SCALE // 2)

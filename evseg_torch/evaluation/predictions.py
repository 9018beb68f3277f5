"""Scoring another method's output on labelled files, with the metrics of :mod:`.labelled`.

A learned EV-IMO-style network (or any other method) is compared with the cascade by scoring its output
on the same labelled files, with the same ignore mask and metrics (``evseg evaluate labelled FILE...
--predictions PRED...``). A prediction is one file per labelled FILE, in one of two forms:

* **per-event labels**: an ``.npy`` integer array :math:`(N,)`, or an ``.npz`` holding one under
  ``field`` (default ``labels``), in the FILE's event order;
* **per-pixel masks at given times**, as EV-IMO's ground truth: an ``.npz`` with ``masks``, integer
  layer ids :math:`(T, H, W)` at the FILE's sensor size, and their times, strictly increasing, either
  ``mask_times`` in seconds (EV-IMO's unit) or ``mask_times_us`` in microseconds, in the events' time
  base (the FILE's ``t_us``). Each event takes the id of its pixel in the mask **nearest in time**, the
  EV-IMO protocol's pairing of a mask with the events around it (:mod:`~evseg_torch.evaluation.evimo` segments
  the window centred on each mask time); midway between two masks it takes the earlier one.

A negative label or mask id means "no cluster" (an outlier), as in
:func:`~evseg_torch.evaluation.labelled.score_labelling`: such an event is wrong for the accuracy,
outside every cluster for the IoU and the boxes, and no cluster for the count error. Only the partition
of the events matters to the clustering metrics, so ids are arbitrary integers: an EV-IMO mask's
``id * 1000`` values score the same as the ids themselves. The dynamic-class metrics of learned maskers
(``dynamic_iou``, ``miou``, ``piou``, ``sr_at_0_5``; see :mod:`.labelled`) read a label > 0 as dynamic
and 0 or below as background, the convention of EV-IMO masks and of binary dynamic masks.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from evseg_torch.errors import ConfigError, ReaderError, ShapeError
from evseg_torch.evaluation.labelled import LabelledScore, load_labelled, score_events
from evseg_torch.io.guard import existing_file, reading
from evseg_torch.io.numpy_files import open_npz

__all__ = [
    "default_method_name",
    "evaluate_predictions",
    "labels_from_masks",
    "load_predictions",
    "match_predictions",
]

WHAT = "predictions file"
_SUFFIXES = (".npz", ".npy")
_MASK_TIME_FIELDS = {"mask_times": 1e6, "mask_times_us": 1.0}


def labels_from_masks(events: np.ndarray, masks: np.ndarray, mask_times_us: np.ndarray) -> np.ndarray:
    """Per-event labels from per-pixel masks: each event takes its pixel's id in the nearest mask in time.

    Args:
        events: canonical events :math:`(N,)` (``t`` in µs; ``x`` the column, ``y`` the row), inside
            the masks' ``(H, W)``.
        masks: integer layer ids :math:`(T, H, W)`, ``T >= 1``.
        mask_times_us: time of each mask in µs, in the events' time base, strictly increasing,
            :math:`(T,)`.

    Returns:
        int64 labels :math:`(N,)`. Midway between two masks an event takes the earlier one; events
        before the first mask or after the last take that mask.

    Raises:
        ShapeError: the masks are not an integer :math:`(T, H, W)` array, the times are not :math:`(T,)`,
            not finite or not strictly increasing.

    Examples:
        >>> from evseg_torch.events import as_events
        >>> events = as_events(np.array([[0.0, 0, 0, 1], [0.004, 0, 0, 1], [0.006, 1, 0, 1]]))
        >>> masks = np.array([[[1, 2]], [[3, 4]]])  # (T, H, W) = (2, 1, 2)
        >>> labels_from_masks(events, masks, np.array([0.0, 10_000.0]))
        array([1, 1, 4])
    """
    masks = np.asarray(masks)
    times = np.asarray(mask_times_us, dtype=np.float64)
    if masks.ndim != 3 or len(masks) == 0 or not np.issubdtype(masks.dtype, np.integer):
        raise ShapeError(
            f"masks must be integer layer ids (T, H, W) with T >= 1, got {masks.dtype} {masks.shape}"
        )
    if times.shape != (len(masks),):
        raise ShapeError(f"mask times must be ({len(masks)},), one per mask, got {times.shape}")
    if not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
        raise ShapeError("mask times must be finite and strictly increasing")
    t_us = events["t"].astype(np.float64)
    after = np.minimum(np.searchsorted(times, t_us, side="left"), len(times) - 1)
    before = np.maximum(after - 1, 0)
    frame = np.where(times[after] - t_us < t_us - times[before], after, before)
    return masks[frame, events["y"], events["x"]].astype(np.int64)


def load_predictions(
    path: str | Path, events: np.ndarray, sensor_size: tuple[int, int], *, field: str = "labels"
) -> np.ndarray:
    """One method's per-event labels for a labelled file's events, from labels or masks (module doc).

    Args:
        path: an ``.npy`` label array, or an ``.npz`` with ``field`` or with ``masks`` and
            ``mask_times`` (seconds) or ``mask_times_us``; ``field`` is used when the file holds both.
        events: the labelled file's canonical events :math:`(N,)`, in its order.
        sensor_size: ``(H, W)`` of the labelled file; masks must have this size.
        field: the ``.npz`` member holding per-event labels.

    Returns:
        int64 labels :math:`(N,)`, negative for no cluster.

    Raises:
        ReaderError: the file is missing, not ``.npy``/``.npz``, unreadable, lacks the fields, or its
            labels are not one integer per event.
        ShapeError: the masks are not integer ids :math:`(T, H, W)` at ``sensor_size``, or their times
            are not one per mask, strictly increasing.
    """
    path = existing_file(path)
    suffix = path.suffix.lower()
    if suffix not in _SUFFIXES:
        raise ReaderError(f"{path}: predictions must be an .npy or .npz file, got {suffix!r}")
    with reading(path, WHAT):
        if suffix == ".npy":
            return _per_event(np.load(path, allow_pickle=False), len(events), "the array")
        with open_npz(path) as npz:
            names = npz.files
            if field in names:
                return _per_event(npz[field], len(events), repr(field))
            if "masks" not in names:
                raise ReaderError(
                    f"no per-event label field {field!r} and no 'masks' (fields: {', '.join(names)})"
                )
            time_fields = [name for name in _MASK_TIME_FIELDS if name in names]
            if len(time_fields) != 1:
                raise ReaderError(
                    "'masks' needs its times in one field, 'mask_times' (seconds) or 'mask_times_us', "
                    f"found {time_fields or 'neither'}"
                )
            masks = npz["masks"]
            # Rounded to the nanosecond: 14000 µs stored as 14000 * 1e-6 s scales back to
            # 13999.999999999998 µs, which would move an event midway between two masks to the later one.
            times = np.round(
                np.asarray(npz[time_fields[0]], dtype=np.float64) * _MASK_TIME_FIELDS[time_fields[0]], 3
            )
        if masks.ndim == 3 and masks.shape[1:] != tuple(sensor_size):
            raise ShapeError(f"masks are {masks.shape[1:]} (H, W) but the sensor is {tuple(sensor_size)}")
        return labels_from_masks(events, masks, times)


def match_predictions(files: Sequence[str | Path], predictions: Sequence[str | Path]) -> list[Path]:
    """The prediction of each labelled file: one per file in order, or ``<stem>.npz``/``.npy`` in a folder.

    Args:
        files: the labelled files.
        predictions: as many prediction files, matched in order; or one folder holding, for each
            labelled file, a file named by its stem with suffix ``.npz`` or ``.npy``.

    Returns:
        One prediction path per labelled file, in their order.

    Raises:
        ConfigError: the counts differ (and ``predictions`` is not one folder).
        ReaderError: the folder lacks a file's prediction, or holds both its ``.npz`` and ``.npy``.
    """
    files, predictions = [Path(f) for f in files], [Path(p) for p in predictions]
    if len(predictions) == 1 and predictions[0].is_dir():
        folder = predictions[0]
        matched = []
        for path in files:
            found = [
                folder / f"{path.stem}{suffix}"
                for suffix in _SUFFIXES
                if (folder / f"{path.stem}{suffix}").is_file()
            ]
            if len(found) != 1:
                problem = "holds no" if not found else "holds both an .npz and an .npy"
                raise ReaderError(f"{folder}: {problem} prediction {path.stem}.npz/.npy for {path}")
            matched.append(found[0])
        return matched
    if len(predictions) != len(files):
        raise ConfigError(
            f"{len(predictions)} predictions for {len(files)} labelled files: give one per file, in order, "
            "or one folder holding <file stem>.npz or .npy"
        )
    return predictions


def default_method_name(predictions: Sequence[str | Path]) -> str:
    """A name for the method whose ``predictions`` are scored: a folder's name, or a lone file's stem.

    Args:
        predictions: prediction paths, as given to :func:`match_predictions`.

    Returns:
        The folder's name for one folder; the file's stem for one file; the name of the folder holding
        them all for several files; else ``"predictions"``.

    Examples:
        >>> default_method_name(["runs/evimo_net/scene_200.npz", "runs/evimo_net/scene_201.npz"])
        'evimo_net'
        >>> default_method_name(["net_output.npy"])
        'net_output'
    """
    paths = [Path(p) for p in predictions]
    if len(paths) == 1:
        return paths[0].resolve().name if paths[0].is_dir() else paths[0].stem
    folders = {p.resolve().parent for p in paths}
    return folders.pop().name if len(folders) == 1 else "predictions"


def evaluate_predictions(
    files: Sequence[str | Path],
    predictions: Sequence[str | Path],
    *,
    method: str | None = None,
    sensor_size: tuple[int, int] | None = None,
    label_field: str = "label",
    ignore_field: str | None = "ambiguous",
    prediction_field: str = "labels",
) -> list[LabelledScore]:
    """Score another method's predictions on labelled files, exactly as the cascade is scored.

    Args:
        files: labelled ``.npz`` files (see :func:`~evseg_torch.evaluation.labelled.load_labelled`).
        predictions: their predictions, matched by :func:`match_predictions`; formats in the module doc.
        method: the method's name in the scores; default :func:`default_method_name`.
        sensor_size: ``(H, W)`` of every file; default from each file.
        label_field, ignore_field: as in :func:`~evseg_torch.evaluation.labelled.load_labelled`.
        prediction_field: the ``.npz`` member of per-event labels (see :func:`load_predictions`).

    Returns:
        One :class:`~evseg_torch.evaluation.labelled.LabelledScore` per file, named by the file's stem,
        with ``method`` set and ``time_ms`` NaN (the method's time is not known).

    Raises:
        ConfigError, ReaderError, ShapeError: as in :func:`match_predictions` and :func:`load_predictions`.
        EventFormatError: as in :func:`~evseg_torch.evaluation.labelled.load_labelled`.
    """
    files = list(files)
    method = default_method_name(predictions) if method is None else method
    scores = []
    for path, prediction in zip(files, match_predictions(files, predictions), strict=True):
        events, labels, ignore, size = load_labelled(
            path, sensor_size, label_field=label_field, ignore_field=ignore_field
        )
        predicted = load_predictions(prediction, events, size, field=prediction_field)
        scores.append(
            score_events(
                predicted, events, labels, ignore, name=Path(path).stem, method=method, dynamic=predicted > 0
            )
        )
    return scores


def _per_event(labels: np.ndarray, n_events: int, what: str) -> np.ndarray:
    if labels.shape != (n_events,) or not np.issubdtype(labels.dtype, np.integer):
        raise ReaderError(
            f"{what} must hold one integer label per event ({n_events}), got {labels.dtype} {labels.shape}"
        )
    return labels.astype(np.int64)

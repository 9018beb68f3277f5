"""Read an ``evseg segment`` result folder back (the files of the README's "Output files").

:func:`load_results` checks the folder's ``schema_version`` against the one this version writes
(:data:`evseg_torch.app.output.SCHEMA_VERSION`) and refuses, in one line, a folder that is not a result, is
unfinished, or was written by a newer evseg. Labels are loaded whole (16 bytes per event); the
per-window models come as :class:`WindowModels`, with their parameters' names and units.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evseg_torch.app.output import SCHEMA_VERSION
from evseg_torch.config import SegmenterConfig, load_config
from evseg_torch.errors import ResultsError
from evseg_torch.tracking import TrackedClusters


@dataclass(frozen=True)
class WindowModels:
    """One segmented window's record of ``models.jsonl``.

    Attributes:
        window: the window's index.
        first_event: index of its first event in the recording.
        n_events: its number of events.
        t_first_us, t_last_us: times of its first and last events, µs in the recording's time base.
        t_ref: the time its events are compensated to, seconds.
        motion_model: the models' family (``translation``, ``affine4``, ``rotation3d``).
        parameters: the parameters' names, in the order of the models' columns.
        units: their units.
        models: row ``k`` is cluster ``k``'s model, float64 :math:`(K, P)`.
        n_level_one_models: size of level one's model pool.
        timings_ms: milliseconds per stage.
        object_ids: each cluster's object id, int64 :math:`(K,)`: 0 the background, and an object keeps
            its id from window to window (:mod:`evseg_torch.tracking`); ``None`` in results written
            before ids existed.
        shared_motion: each cluster's motion group, int64 :math:`(K,)`: the lowest index of the clusters
            moving alike (within 1 px over the window); ``None`` likewise.
        centres: the median ``[x, y]`` of each cluster's compensated events at ``t_ref``, px, float64
            :math:`(K, 2)` (NaN for a cluster without events); ``None`` likewise.
        boxes: each cluster's compensated events as ``[x, y, w, h]`` at ``t_ref``, px, float64
            :math:`(K, 4)` (NaN for a cluster without events); ``None`` likewise.
    """

    window: int
    first_event: int
    n_events: int
    t_first_us: int | None
    t_last_us: int | None
    t_ref: float
    motion_model: str
    parameters: tuple[str, ...]
    units: tuple[str, ...]
    models: np.ndarray
    n_level_one_models: int
    timings_ms: dict[str, float]
    object_ids: np.ndarray | None = None
    shared_motion: np.ndarray | None = None
    centres: np.ndarray | None = None
    boxes: np.ndarray | None = None


@dataclass(frozen=True)
class SegmentationResults:
    """A result folder, loaded.

    Attributes:
        folder: where it was read from.
        labels: each event's cluster within its window, int64 :math:`(N,)`; ``-1`` for events in no window.
        window: each event's window, int64 :math:`(N,)`; ``-1`` for events in no window.
        windows: the per-window models, in window order.
        summary: ``summary.json`` as a dict.
        config: the configuration the results were made with.
        images: the per-window figures (``images/NNNNNN.png``), sorted; empty without ``--save-images``.
        video: ``video.mp4``, or None without ``--video``.
    """

    folder: Path
    labels: np.ndarray
    window: np.ndarray
    windows: tuple[WindowModels, ...]
    summary: dict
    config: SegmenterConfig
    images: tuple[Path, ...]
    video: Path | None


def load_results(folder: str | Path) -> SegmentationResults:
    """Load the results ``evseg segment`` wrote for one recording.

    Args:
        folder: the recording's output folder, ``OUT/<input name>``.

    Raises:
        ResultsError: the folder is missing, holds no finished results, is of a newer schema, or a file
            in it is unreadable.
    """
    folder = Path(folder)
    summary_path = folder / "summary.json"
    if not summary_path.is_file():
        what = (
            "does not exist" if not folder.exists() else "has no summary.json (not a result, or unfinished)"
        )
        raise ResultsError(f"{folder} {what}")
    summary = _json(summary_path, summary_path.read_text())
    _check_version(summary, summary_path)
    try:
        with np.load(folder / "labels.npz") as data:
            labels, window = data["labels"], data["window"]
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as err:
        raise ResultsError(f"{folder / 'labels.npz'}: cannot read labels and window: {err}") from None
    windows = []
    try:
        lines = (folder / "models.jsonl").read_text().splitlines()
    except OSError as err:
        raise ResultsError(f"{folder / 'models.jsonl'}: {err.strerror or err}") from None
    for number, line in enumerate(lines, start=1):
        where = f"{folder / 'models.jsonl'} line {number}"
        record = _json(where, line)
        _check_version(record, where)
        fields = {name: record.get(name) for name in WindowModels.__dataclass_fields__}
        n_params = len(fields["parameters"] or ())
        fields.update(
            parameters=tuple(fields["parameters"] or ()),
            units=tuple(fields["units"] or ()),
            models=np.asarray(fields["models"], dtype=np.float64).reshape(-1, n_params),
        )
        if "object_ids" in record:
            tracked = TrackedClusters.from_record(record)
            fields.update(
                object_ids=tracked.ids,
                shared_motion=np.asarray(record["shared_motion"], dtype=np.int64),
                centres=tracked.centres,
                boxes=tracked.boxes,
            )
        windows.append(WindowModels(**fields))
    video = folder / "video.mp4"
    return SegmentationResults(
        folder=folder,
        labels=labels,
        window=window,
        windows=tuple(windows),
        summary=summary,
        config=load_config(folder / "config.yaml"),
        images=tuple(sorted((folder / "images").glob("*.png"))),
        video=video if video.is_file() else None,
    )


def _json(where, text: str) -> dict:
    try:
        value = json.loads(text)
    except json.JSONDecodeError as err:
        raise ResultsError(f"{where}: not valid JSON ({err.msg})") from None
    if not isinstance(value, dict):
        raise ResultsError(f"{where}: expected a JSON object")
    return value


def _check_version(record: dict, where) -> None:
    version = record.get("schema_version")
    if not isinstance(version, int):
        raise ResultsError(
            f"{where}: no schema_version (written before results were versioned); segment again"
        )
    if version > SCHEMA_VERSION:
        raise ResultsError(
            f"{where}: schema version {version} is newer than this evseg reads"
            f" ({SCHEMA_VERSION}); upgrade evseg"
        )

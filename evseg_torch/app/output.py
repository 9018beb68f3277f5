"""Writers of segmentation results: streaming, resumable, and published only when complete.

The files of a result folder, their fields, dtypes, units and version (:data:`SCHEMA_VERSION`) are
documented in the README's "Output files" section, which a test compares with what is written here;
:func:`evseg_torch.app.results.load_results` reads a folder back. Figures and video frames come from
:func:`evseg_torch.viz.panels.render_fig1`.

While a run goes on, everything is written into the folder's hidden ``.partial/`` with a checkpoint
(``state.json``) after every batch of windows; nothing partial is ever presented as a result. When the
run ends, each finished file is moved into the folder by a rename, ``summary.json`` last, so a folder
with a ``summary.json`` and no ``.partial/`` is complete. A stopped run (killed, interrupted, out of disk)
keeps its ``.partial/``; :class:`SegmentationWriter` with ``resume=True`` truncates the files to the last
checkpoint and carries on from there, provided the run's identity (input file, configuration, options
that change results) is the same; the last window's models, which the next window starts from, and
its clusters' object ids, centres and boxes, which the next window's ids continue
(:mod:`evseg_torch.tracking`), are read back from ``models.jsonl``. Video frames wait as PNGs in
``.partial/frames/`` and are encoded at the end, so that a resumed run's video holds every window too.
"""

from __future__ import annotations

import json
import os
import shutil
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evseg_torch.config import SegmenterConfig, dump_config
from evseg_torch.errors import EvsegError
from evseg_torch.motion import MOTION_MODELS
from evseg_torch.tracking import TrackedClusters

# Raised whenever a field is renamed, removed or changes meaning; readers refuse newer versions.
SCHEMA_VERSION = 1
PARTIAL = ".partial"
_STATE = "state.json"
# In publishing order.
_FINISHED = ("config.yaml", "models.jsonl", "labels.npz", "images", "video.mp4", "summary.json")


class OutputExistsError(EvsegError, FileExistsError):
    """The output folder already holds results and neither overwriting nor resuming was asked for."""


class ResumeError(EvsegError):
    """A stopped run cannot be resumed as asked: its input or configuration changed."""


@dataclass(frozen=True)
class ResumePoint:
    """Where a run carries on; the defaults are a fresh run's start.

    Attributes:
        next_window: index of the first window still to segment.
        models: the models of the last window written, :math:`(M, P)` float64, or ``None`` if none was.
        objects: the last window's clusters for the object tracker, or ``None`` if none was written.
        next_object_id: one more than the largest object id written (1 if none was).
    """

    next_window: int = 0
    models: np.ndarray | None = None
    objects: TrackedClusters | None = None
    next_object_id: int = 1


def folder_state(folder: str | Path) -> str:
    """``"empty"`` (absent or empty), ``"finished"``, ``"stopped"`` (a run to resume) or ``"other"``."""
    folder = Path(folder)
    if (folder / PARTIAL / _STATE).is_file():
        return "stopped"
    if not folder.is_dir() or not any(folder.iterdir()):
        return "empty"
    return "finished" if (folder / "summary.json").is_file() else "other"


def holds_run(folder: str | Path, run: dict) -> bool:
    """Whether ``folder`` holds a stopped or finished run with identity ``run`` (see SegmentationWriter)."""
    recorded = _recorded_run(Path(folder), folder_state(folder))
    return recorded is not None and recorded == _plain(run)


def _recorded_run(folder: Path, state: str) -> dict | None:
    """The identity of the run a ``"stopped"`` or ``"finished"`` folder holds (``None`` otherwise)."""
    if state == "stopped":
        return json.loads((folder / PARTIAL / _STATE).read_text()).get("run", {})
    if state == "finished":
        return json.loads((folder / "summary.json").read_text()).get("run", {})
    return None


class SegmentationWriter:
    """Write one recording's per-window results as they come; use as a context manager.

    An :class:`~evseg_torch.errors.EvsegError` inside the block (a bad input) removes the partial
    results; any other exit from it (an interrupt, a full disk) keeps them to resume from.

    Args:
        folder: output folder of this recording; created if missing.
        config: the configuration used, copied as ``config.yaml``.
        run: what identifies the run (input, options that change results), JSON-serialisable; a resumed
            run must match it, and a folder holding another input's results is never replaced.
        save_images: also write one figure per window into ``images/``.
        video: also write ``video.mp4``, one frame per window (needs the ``video`` extra).
        overwrite: replace this input's existing results, finished or stopped.
        resume: continue a stopped run from its last checkpoint (:attr:`resume_point`, which is a fresh
            start's otherwise); for a finished run nothing is written and :attr:`summary` holds its summary.

    Raises:
        OutputExistsError: the folder holds results and neither ``overwrite`` nor ``resume`` applies, or it
            holds another input's results.
        ResumeError: the stopped run's input, configuration or options differ from ``run``.
    """

    def __init__(
        self,
        folder: str | Path,
        config: SegmenterConfig,
        run: dict | None = None,
        save_images: bool = False,
        overwrite: bool = False,
        resume: bool = False,
        video: bool = False,
    ):
        if video:  # before anything is written: a missing extra leaves no partial folder
            from evseg_torch.viz.video import require_av

            require_av()
        self.video = video
        self.folder = Path(folder)
        self.partial = self.folder / PARTIAL
        self.run = _plain(run or {})
        self.save_images = save_images
        self.timings: dict[str, list[float]] = {}
        self.written = self.n_windows = 0
        self.wall_s = 0.0
        self.resume_point = ResumePoint()
        self.summary: dict | None = None
        state = folder_state(self.folder)
        self._check_owner(state)
        if state == "stopped" and resume and self._reopen():
            return
        state = folder_state(self.folder)  # a run stopped while publishing is finished now
        if state == "finished" and resume:
            difference = _first_difference(_recorded_run(self.folder, state), self.run)
            if difference:
                raise ResumeError(
                    f"{self.folder} holds finished results, but {difference}; pass --overwrite to redo them"
                )
            self.summary = json.loads((self.folder / "summary.json").read_text())
            return
        if state != "empty":
            if not overwrite:
                raise OutputExistsError(_refusal(self.folder, state))
            shutil.rmtree(self.folder)
        self.partial.mkdir(parents=True)
        dump_config(config, self.partial / "config.yaml")
        self._open("wb", "w")
        self.checkpoint()

    def __enter__(self) -> SegmentationWriter:
        return self

    def __exit__(self, kind, error, traceback) -> None:
        if kind is None:
            return
        if issubclass(kind, EvsegError):
            self.abort()
        else:
            self._close_files()

    def abort(self) -> None:
        """Close everything and remove the results, e.g. when the input turns out to be bad."""
        self._close_files()
        shutil.rmtree(self.folder, ignore_errors=True)

    def add(self, segmentation, first_event: int = 0) -> None:
        """Record one window's :class:`~evseg_torch.pipeline.Segmentation`.

        Args:
            segmentation: the window; its ``offset`` is its first event's index among the events the
                labels cover.
            first_event: index in the input of the first event the labels cover (the same every call).
        """
        index, offset = segmentation.window_index, segmentation.offset
        labels = np.asarray(segmentation.labels, dtype=np.int64)
        if offset > self.written:
            self._write_labels(np.full(offset - self.written, -1), np.full(offset - self.written, -1))
        fresh = labels[max(self.written - offset, 0) :]
        self._write_labels(fresh, np.full(len(fresh), index))
        model = MOTION_MODELS[segmentation.motion_model]
        times = segmentation.events["t"]
        record = {
            "schema_version": SCHEMA_VERSION,
            "window": index,
            "first_event": int(first_event + offset),
            "n_events": len(labels),
            "t_first_us": int(times[0]) if len(times) else None,
            "t_last_us": int(times[-1]) if len(times) else None,
            "t_ref": float(segmentation.t_ref),
            "motion_model": segmentation.motion_model,
            "parameters": list(model.param_names),
            "units": list(model.param_units),
            "models": np.asarray(segmentation.models, dtype=np.float64).tolist(),
            "object_ids": _ints(segmentation.object_ids),
            "shared_motion": _ints(segmentation.shared_motion),
            "centres": _rows(segmentation.centres),
            "boxes": _rows(segmentation.boxes),
            "n_level_one_models": len(segmentation.level_one_models),
            "timings_ms": {stage: float(v) for stage, v in segmentation.timings_ms.items()},
        }
        self._models.write(json.dumps(record) + "\n")
        self._count(record)
        self._next_window = index + 1
        if self.save_images or self.video:
            from evseg_torch.viz.panels import VIDEO_PANELS, render_fig1, write_png

            if self.save_images:
                image = render_fig1(segmentation, title=f"window {index}", ids=record["object_ids"])
                write_png(image, self.partial / "images" / f"{index:06d}.png")
            if self.video:
                frame = render_fig1(
                    segmentation,
                    title=f"window {index}",
                    ids=record["object_ids"],
                    panels=VIDEO_PANELS,
                    crop=False,
                )
                write_png(frame, self.partial / "frames" / f"{index:06d}.png")

    def checkpoint(self, wall_s: float = 0.0) -> None:
        """Record that everything added so far is complete: a stopped run resumes from here.

        Args:
            wall_s: seconds spent since the last checkpoint, added to the run's total.
        """
        for handle in (self._labels, self._windows, self._models):
            handle.flush()
        self.wall_s += wall_s
        self._write_state(finished=False)

    def close(self, n_events: int | None, wall_s: float, extra: dict | None = None) -> dict:
        """Finish ``labels.npz`` and ``summary.json`` and publish the results; returns the summary.

        Args:
            n_events: events the labels cover (those after the last window are labelled -1); ``None``
                for exactly those written.
            wall_s: seconds spent since the last checkpoint.
            extra: more fields of ``summary.json``.
        """
        if n_events is not None and n_events > self.written:
            self._write_labels(np.full(n_events - self.written, -1), np.full(n_events - self.written, -1))
        self._close_files()
        with zipfile.ZipFile(
            self.partial / "labels.npz", "w", compression=zipfile.ZIP_STORED, allowZip64=True
        ) as archive:
            for name in ("labels", "window"):
                _stream_npy(archive, name, self.partial / f"{name}.bin", self.written)
        self.wall_s += wall_s
        frames = self._encode_video() if self.video else None
        summary = {
            "schema_version": SCHEMA_VERSION,
            "events": int(self.written),
            "windows": self.n_windows,
            "wall_s": self.wall_s,
            "events_per_s": self.written / self.wall_s if self.wall_s > 0 else None,
            "video_frames": frames,
            "timings_ms": {
                stage: {"median": float(np.median(v)), "mean": float(np.mean(v)), "max": float(np.max(v))}
                for stage, v in self.timings.items()
            },
            **(extra or {}),
            "run": self.run,
        }
        (self.partial / "summary.json").write_text(json.dumps(summary, indent=2))
        self._write_state(finished=True)
        publish(self.folder)
        return summary

    def _encode_video(self) -> int:
        """Encode the waiting frames, in window order, into ``video.mp4``; returns the frame count."""
        import cv2

        from evseg_torch.viz.video import VideoWriter

        video = VideoWriter(self.partial / "video.mp4")
        try:
            for path in sorted((self.partial / "frames").glob("*.png")):
                video.write(cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB))
        finally:
            video.close()
        shutil.rmtree(self.partial / "frames")
        return video.n_frames

    def _open(self, binary: str, text: str) -> None:
        self._labels = open(self.partial / "labels.bin", binary)
        self._windows = open(self.partial / "window.bin", binary)
        self._models = open(self.partial / "models.jsonl", text)
        self._next_window = 0
        for wanted, name in ((self.save_images, "images"), (self.video, "frames")):
            if wanted:
                (self.partial / name).mkdir(exist_ok=True)

    def _reopen(self) -> bool:
        """Truncate a stopped run's files to its last checkpoint and carry on from there; ``False`` when
        the run had finished and was stopped while publishing (which this completes)."""
        state = json.loads((self.partial / _STATE).read_text())
        difference = _first_difference(state.get("run", {}), self.run)
        if difference:
            raise ResumeError(f"cannot resume {self.folder}: {difference}")
        if state.get("finished"):
            publish(self.folder)
            return False
        self.written, self.wall_s = state["written"], state["wall_s"]
        for name in ("labels.bin", "window.bin"):
            os.truncate(self.partial / name, 8 * self.written)
        os.truncate(self.partial / "models.jsonl", state["models_bytes"])
        last, largest_id = None, 0
        with open(self.partial / "models.jsonl") as rows:
            for line in rows:
                last = json.loads(line)
                if "object_ids" not in last:
                    raise ResumeError(
                        f"cannot resume {self.folder}: its windows were written by an older evseg without "
                        "object ids; pass --overwrite to start again"
                    )
                self._count(last)
                largest_id = max([largest_id, *last["object_ids"]])
        self._open("ab", "a")
        self._next_window = state["next_window"]
        models = None if last is None else np.array(last["models"], dtype=np.float64)
        objects = None if last is None else TrackedClusters.from_record(last)
        self.resume_point = ResumePoint(self._next_window, models, objects, largest_id + 1)
        return True

    def _count(self, record: dict) -> None:
        for stage, value in record["timings_ms"].items():
            self.timings.setdefault(stage, []).append(value)
        self.n_windows += 1

    def _write_state(self, finished: bool) -> None:
        state = {
            "run": self.run,
            "finished": finished,
            "n_windows": self.n_windows,
            "next_window": self._next_window,
            "written": self.written,
            "models_bytes": (self.partial / "models.jsonl").stat().st_size,
            "wall_s": self.wall_s,
        }
        scratch = self.partial / f"{_STATE}.new"
        scratch.write_text(json.dumps(state))
        os.replace(scratch, self.partial / _STATE)

    def _check_owner(self, state: str) -> None:
        """Refuse, whatever the flags, to replace or resume another input's results."""
        recorded = _recorded_run(self.folder, state)
        if recorded is None or "input" not in self.run:
            return
        theirs, ours = recorded.get("input"), self.run["input"]
        if theirs is not None and theirs.get("path") != ours.get("path"):
            raise OutputExistsError(
                f"output folder {self.folder} holds the results of {theirs.get('path')}, not of "
                f"{ours.get('path')}; choose another --out"
            )

    def _close_files(self) -> None:
        for name in ("_labels", "_windows", "_models"):
            handle = getattr(self, name, None)
            if handle is not None:
                handle.close()

    def _write_labels(self, labels: np.ndarray, windows: np.ndarray) -> None:
        labels.astype("<i8").tofile(self._labels)
        windows.astype("<i8").tofile(self._windows)
        self.written += len(labels)


def publish(folder: str | Path) -> None:
    """Move a finished run's files from ``.partial/`` into ``folder``, ``summary.json`` last.

    Each file moves by a rename, so each appears whole; a publication that was itself stopped is
    completed by calling this again (what already moved is skipped).
    """
    folder = Path(folder)
    partial = folder / PARTIAL
    for name in _FINISHED:
        if (partial / name).exists():
            if (folder / name).is_dir():
                shutil.rmtree(folder / name)
            os.replace(partial / name, folder / name)
    shutil.rmtree(partial)


def _ints(values) -> list[int]:
    return np.asarray(values, dtype=np.int64).tolist()


def _rows(values) -> list:
    """Rows of floats as lists, a row with NaN (a cluster without events) as ``None``: JSON has no NaN."""
    return [None if np.isnan(row).any() else row.tolist() for row in np.asarray(values, dtype=np.float64)]


def _refusal(folder: Path, state: str) -> str:
    if state == "stopped":
        return (
            f"output folder {folder} holds a stopped run; pass --resume to continue it or --overwrite to "
            "start again"
        )
    if state == "finished":
        return f"output folder {folder} holds finished results; pass --overwrite to replace them"
    return f"output folder {folder} is not empty; pass --overwrite to replace it"


def _first_difference(before, now, where: str = "") -> str | None:
    """The first key path at which two JSON-like values differ, described for a message; ``None`` if equal."""
    if isinstance(before, dict) and isinstance(now, dict):
        for key in sorted(set(before) | set(now)):
            found = _first_difference(before.get(key), now.get(key), f"{where}.{key}" if where else key)
            if found:
                return found
        return None
    if before != now:
        return f"{where or 'the run'} differs ({_short(before)} then, {_short(now)} now)"
    return None


def _short(value) -> str:
    text = json.dumps(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _plain(value):
    """``value`` as it reads back from JSON (tuples become lists), so identities compare equal."""
    return json.loads(json.dumps(value))


def _stream_npy(archive: zipfile.ZipFile, name: str, raw: Path, count: int) -> None:
    """Add a raw little-endian int64 file to an npz member without loading it into memory."""
    with archive.open(f"{name}.npy", "w", force_zip64=True) as member, open(raw, "rb") as source:
        np.lib.format.write_array_header_1_0(
            member, {"descr": "<i8", "fortran_order": False, "shape": (count,)}
        )
        shutil.copyfileobj(source, member, length=1 << 22)

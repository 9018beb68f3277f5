"""Writers of segmentation results, streaming so memory stays bounded by one window.

The files of a result folder, their fields, dtypes, units and version (:data:`SCHEMA_VERSION`) are
documented in the README's "Output files" section, which a test compares with what is written here;
:func:`evseg_torch.results.load_results` reads a folder back. Figures and video frames come from
:func:`evseg_torch.panels.render_fig1`.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from evseg_torch.config import SegmenterConfig, dump_config
from evseg_torch.errors import EvsegError
from evseg_torch.motion import MOTION_MODELS

# Raised whenever a field is renamed, removed or changes meaning; readers refuse newer versions.
SCHEMA_VERSION = 1


class OutputExistsError(EvsegError, FileExistsError):
    """The output folder already holds results and overwriting was not asked for."""


class SegmentationWriter:
    """Write one recording's per-window results as they come; as a context manager, an error inside
    the block removes the partial results.

    Args:
        folder: output folder of this recording; created if missing.
        config: the configuration used, copied as ``config.yaml``.
        save_images: also write one Fig. 1 PNG per window (``images/NNNNNN.png``).
        video: also write ``video.mp4``, one frame per window (needs the ``video`` extra).
        overwrite: replace existing results; otherwise an existing non-empty folder is an error.
    """

    def __init__(
        self,
        folder: str | Path,
        config: SegmenterConfig,
        save_images: bool = False,
        overwrite: bool = False,
        video: bool = False,
    ):
        if video:  # before anything is written: a missing extra leaves no partial folder
            from evseg_torch.video import require_av

            require_av()
        self.folder = Path(folder)
        if self.folder.exists() and any(self.folder.iterdir()):
            if not overwrite:
                raise OutputExistsError(
                    f"output folder {self.folder} is not empty; pass --overwrite to replace it"
                )
            shutil.rmtree(self.folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        dump_config(config, self.folder / "config.yaml")
        self.save_images = save_images
        if save_images:
            (self.folder / "images").mkdir()
        self._scratch = tempfile.TemporaryDirectory(dir=self.folder, prefix=".partial-")
        self._labels = open(Path(self._scratch.name) / "labels.bin", "wb")
        self._windows = open(Path(self._scratch.name) / "window.bin", "wb")
        self._models = open(self.folder / "models.jsonl", "w")
        self.written = 0
        self.timings: dict[str, list[float]] = {}
        self.n_windows = 0
        self._video = None
        if video:
            from evseg_torch.video import VideoWriter

            self._video = VideoWriter(self.folder / "video.mp4")

    def __enter__(self) -> SegmentationWriter:
        return self

    def __exit__(self, kind, error, traceback) -> None:
        if kind is not None:
            self.abort()

    def abort(self) -> None:
        """Close everything and remove the partial results, e.g. when the input turns out to be bad."""
        for handle in (self._labels, self._windows, self._models):
            handle.close()
        if self._video is not None:
            self._video.close()
        self._scratch.cleanup()
        shutil.rmtree(self.folder, ignore_errors=True)

    def add(self, segmentation) -> None:
        """Record one window's :class:`~evseg_torch.pipeline.Segmentation` (placed by its ``offset``)."""
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
            "first_event": int(offset),
            "n_events": len(labels),
            "t_first_us": int(times[0]) if len(times) else None,
            "t_last_us": int(times[-1]) if len(times) else None,
            "t_ref": float(segmentation.t_ref),
            "motion_model": segmentation.motion_model,
            "parameters": list(model.param_names),
            "units": list(model.param_units),
            "models": np.asarray(segmentation.models, dtype=np.float64).tolist(),
            "n_level_one_models": len(segmentation.level_one_models),
            "timings_ms": {stage: float(v) for stage, v in segmentation.timings_ms.items()},
        }
        self._models.write(json.dumps(record) + "\n")
        for stage, value in segmentation.timings_ms.items():
            self.timings.setdefault(stage, []).append(value)
        self.n_windows += 1
        if self.save_images or self._video is not None:
            from evseg_torch.panels import VIDEO_PANELS, render_fig1, write_png

            if self.save_images:
                image = render_fig1(segmentation, title=f"window {index}")
                write_png(image, self.folder / "images" / f"{index:06d}.png")
            if self._video is not None:
                frame = render_fig1(segmentation, title=f"window {index}", panels=VIDEO_PANELS, crop=False)
                self._video.write(frame)

    def close(self, n_events: int, wall_s: float, extra: dict | None = None) -> dict:
        """Finish ``labels.npz`` and write ``summary.json``; returns the summary."""
        if n_events > self.written:
            self._write_labels(np.full(n_events - self.written, -1), np.full(n_events - self.written, -1))
        self._labels.close()
        self._windows.close()
        self._models.close()
        if self._video is not None:
            self._video.close()
        with zipfile.ZipFile(
            self.folder / "labels.npz", "w", compression=zipfile.ZIP_STORED, allowZip64=True
        ) as archive:
            for name in ("labels", "window"):
                _stream_npy(archive, name, Path(self._scratch.name) / f"{name}.bin", self.written)
        self._scratch.cleanup()
        summary = {
            "schema_version": SCHEMA_VERSION,
            "events": int(n_events),
            "windows": self.n_windows,
            "wall_s": float(wall_s),
            "events_per_s": n_events / wall_s if wall_s > 0 else None,
            "video_frames": self._video.n_frames if self._video is not None else None,
            "timings_ms": {
                stage: {"median": float(np.median(v)), "mean": float(np.mean(v)), "max": float(np.max(v))}
                for stage, v in self.timings.items()
            },
            **(extra or {}),
        }
        (self.folder / "summary.json").write_text(json.dumps(summary, indent=2))
        return summary

    def _write_labels(self, labels: np.ndarray, windows: np.ndarray) -> None:
        labels.astype("<i8").tofile(self._labels)
        windows.astype("<i8").tofile(self._windows)
        self.written += len(labels)


def _stream_npy(archive: zipfile.ZipFile, name: str, raw: Path, count: int) -> None:
    """Add a raw little-endian int64 file to an npz member without loading it into memory."""
    with archive.open(f"{name}.npy", "w", force_zip64=True) as member, open(raw, "rb") as source:
        np.lib.format.write_array_header_1_0(
            member, {"descr": "<i8", "fortran_order": False, "shape": (count,)}
        )
        shutil.copyfileobj(source, member, length=1 << 22)

"""The jobs of ``evseg segment``: each input, its output folder and how to segment it.

* **One folder per input**, named by the input's stem; when two inputs of a run share a stem, each of
  them is named by its parent folders too (``eed_occlusions-events``), as many as tell them apart
  (:func:`output_folders`). A folder never receives another input's results (:mod:`evseg_torch.app.output`).
* **Planning** (:func:`plan_jobs`): each input's format and sensor size are checked before any is
  segmented; with ``keep_going`` an input that cannot be read is reported (:func:`failure`, one line) and
  left out.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from evseg_torch.config import SegmenterConfig, config_to_dict, replace_config
from evseg_torch.errors import EvsegError

log = logging.getLogger("evseg")


def output_folders(inputs: Sequence[str | Path], out: str | Path) -> list[Path]:
    """The output folder of each input: ``out/<stem>``, or with parent folders' names where stems collide.

    Args:
        inputs: the run's input paths.
        out: the output root.

    Returns:
        One folder per input, all different.

    Raises:
        EvsegError: the same input is given twice.

    Examples:
        >>> [p.name for p in output_folders(["a/x/events.txt", "b/y/events.txt", "c.npy"], "out")]
        ['x-events', 'y-events', 'c']
    """
    paths = [Path(path).resolve() for path in inputs]
    seen = {}
    for given, path in zip(inputs, paths, strict=True):
        if path in seen:
            raise EvsegError(f"{given} is given twice (as {seen[path]} too)")
        seen[path] = given
    depth = [0] * len(paths)
    while True:
        names = [_name(path, levels) for path, levels in zip(paths, depth, strict=True)]
        clashes = {name for name in names if names.count(name) > 1}
        if not clashes:
            return [Path(out) / name for name in names]
        depth = [levels + 1 if name in clashes else levels for name, levels in zip(names, depth, strict=True)]


def _name(path: Path, levels: int) -> str:
    parents = [parent.name for parent in path.parents if parent.name][:levels]
    return "-".join([*reversed(parents), path.name if path.is_dir() else path.stem])


@dataclass(frozen=True)
class Job:
    """One input of ``evseg segment`` and how to segment it.

    Attributes:
        path: the recording.
        out: its output folder.
        sensor_size: ``(H, W)`` to segment with (see :func:`evseg_torch.io.resolve_sensor_size`).
        config: the configuration.
        start_s, end_s: segment only the events from ``start_s`` to before ``end_s`` seconds after the
            recording's first event (``None``: from the first, to the last).
        max_windows: segment at most this many windows from the start (``None``: all).
        batch_size: as in :meth:`~evseg_torch.pipeline.CascadedSegmenter.stream`.
        workers: processes that share out each batch's windows (:class:`~evseg_torch.app.workers.WindowPool`),
            at most ``batch_size``; 1 segments in this process.
        save_images: write one figure per window.
        video: write ``video.mp4``, one frame per window.
        overwrite, resume: as in :class:`~evseg_torch.app.output.SegmentationWriter`.
        chunk_size: events read at a time.
        topic: ROS bags: the topic of event arrays (``None``: the first).
        device: torch device of level two.
    """

    path: Path
    out: Path
    sensor_size: tuple[int, int]
    config: SegmenterConfig
    start_s: float | None = None
    end_s: float | None = None
    max_windows: int | None = None
    batch_size: int = 1
    workers: int = 1
    save_images: bool = False
    video: bool = False
    overwrite: bool = False
    resume: bool = False
    chunk_size: int = 1_000_000
    topic: str | None = None
    device: str = "cpu"

    def identity(self) -> dict:
        """What a resumed run must share with the stopped one: input, config and result-changing options."""
        stat = self.path.stat()
        return {
            "input": {"path": str(self.path.resolve()), "bytes": stat.st_size, "mtime_ns": stat.st_mtime_ns},
            "config": config_to_dict(self.config),
            "options": {
                "sensor_size": list(self.sensor_size),
                "topic": self.topic,
                "start_s": self.start_s,
                "end_s": self.end_s,
                "max_windows": self.max_windows,
                "batch_size": self.batch_size,
                "save_images": self.save_images,
                "video": self.video,
            },
        }


def plan_jobs(
    inputs: Sequence[str],
    out: str | Path,
    config: SegmenterConfig,
    *,
    sensor_size: tuple[int, int] | None = None,
    topic: str | None = None,
    chunk_size: int = 1_000_000,
    workers: int = 1,
    keep_going: bool = False,
    **options,
) -> tuple[list[Job], list[str]]:
    """The jobs of a run: each input's folder (:func:`output_folders`), sensor size and options.

    Args:
        inputs: the run's input paths, each a file of a known format or a folder of a known layout.
        out: the output root.
        config: the configuration.
        sensor_size: ``(H, W)`` for files that store none (see :func:`evseg_torch.io.resolve_sensor_size`);
            with neither, the smallest size that holds the events (one extra pass, logged).
        topic, chunk_size: as in :class:`Job`.
        workers: the run's processes: with one input they share out its windows, when its batches hold
            at least as many (otherwise one process runs, with a warning); with several, the files.
        keep_going: report an input that cannot be read (one line) and plan the others.
        **options: the other fields of :class:`Job` (``start_s``, ``end_s``, ``max_windows``,
            ``batch_size``, ``save_images``, ``video``, ``overwrite``, ``resume``, ``device``).

    Returns:
        The jobs, in input order, and (with ``keep_going``) the lines reporting the inputs left out.

    Raises:
        EvsegError: the same input is given twice, or, without ``keep_going``, an input is not a known
            format or its sensor size is wrong.
        OSError: an input cannot be read, without ``keep_going``.
    """
    from evseg_torch.io import reader_for, resolve_sensor_size, scan_sensor_size

    batch_size = options.get("batch_size", 1)
    workers_per_file = 1
    if len(inputs) == 1 and workers > 1:
        if batch_size < workers:
            log.warning(
                "evseg: --workers %d has nothing to share with --batch-size %d on one input: one process "
                "runs (pass --batch-size %d or more to share each batch's windows)",
                workers,
                batch_size,
                workers,
            )
        else:
            workers_per_file = workers
    jobs, failed = [], []
    folders = output_folders(inputs, out)
    for name, folder in zip(inputs, folders, strict=True):
        try:
            reader_for(name)  # a file of a known format or a folder of a known layout
            path = Path(name)
            size = resolve_sensor_size(path, sensor_size, topic=topic)
            if size is None:
                size = scan_sensor_size(path, chunk_size, topic=topic)
                log.info(
                    "%s stores no sensor size: %dx%d, the smallest that holds its events (or pass "
                    "--sensor-size HxW)",
                    path.name,
                    *size,
                )
        except (EvsegError, OSError) as err:
            if not keep_going:
                raise
            failed.append(failure(name, err))
            continue
        jobs.append(
            Job(
                path=path,
                out=folder,
                sensor_size=size,
                config=config,
                workers=workers_per_file,
                chunk_size=chunk_size,
                topic=topic,
                **options,
            )
        )
    return jobs, failed


def failure(path, err: BaseException) -> str:
    """Report an input that failed on standard error at once, as one line naming it; returns the line."""
    message = one_line(err)
    if str(path) not in message:
        message = f"{path}: {message}"
    print(f"evseg: error: {message}", file=sys.stderr, flush=True)
    return message


def with_window(config: SegmenterConfig, window_ms=None, stride_ms=None, events_per_window=None):
    """``config`` with the window geometry given on the command line (``None`` keeps the config's)."""
    if events_per_window is not None:
        return replace_config(config, events_per_window=events_per_window)
    overrides = {k: v for k, v in {"window_ms": window_ms, "stride_ms": stride_ms}.items() if v is not None}
    return replace_config(config, **overrides)


def one_line(err: BaseException) -> str:
    """An exception as one line of text."""
    return " ".join(str(err).split()) or type(err).__name__

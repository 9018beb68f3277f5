"""Segmenting recordings into result folders: what ``evseg segment`` does for each input.

* **One folder per input**, named by the input's stem; when two inputs of a run share a stem, each of
  them is named by its parent folders too (``eed_occlusions-events``), as many as tell them apart
  (:func:`output_folders`). A folder never receives another input's results (:mod:`evseg_torch.app.output`).
* **Resumable**: results go to the folder's ``.partial/`` with a checkpoint after every batch of windows
  and are published when complete; a stopped run resumes from its checkpoint and ends with the files an
  uninterrupted run writes (windows after a checkpoint are segmented again, from the same models, and
  their object ids continue the last window's as they would have).
* **Stopping**: SIGTERM and SIGINT both raise :class:`Stopped` in the main process
  (:func:`stop_on_signals`); the flag it also sets is checked after every window, so an interrupt that
  lands where Python ignores exceptions (a finaliser) still stops the run at the next window.
* **Many inputs**: one after another, or file by file in worker processes (:func:`segment_files`); with
  ``keep_going`` a bad input is reported and the others are segmented. :mod:`evseg_torch.app.cluster`
  runs the same jobs as tasks on a Dask cluster, each by :func:`segment_file`.
"""

from __future__ import annotations

import logging
import multiprocessing
import signal
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evseg_torch.app.workers import WindowPool, worker_signals
from evseg_torch.config import SegmenterConfig, config_to_dict, replace_config
from evseg_torch.errors import EvsegError

log = logging.getLogger("evseg")


class Stopped(KeyboardInterrupt):
    """The run was asked to stop by a signal (SIGINT or SIGTERM); ``signum`` says which."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


_stop_requested: list[int] = []


@contextmanager
def stop_on_signals() -> Iterator[None]:
    """Within the block, SIGTERM and SIGINT raise :class:`Stopped` (main thread only)."""

    def stop(signum, frame):
        _stop_requested.append(signum)
        raise Stopped(signum)

    previous = {number: signal.signal(number, stop) for number in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
        _stop_requested.clear()


def stopped_by(err: BaseException) -> Stopped | None:
    """The :class:`Stopped` that ``err`` was raised from (its cause or context, at any depth), or ``None``."""
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, Stopped):
            return err
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return None


def _raise_if_stopped() -> None:
    if _stop_requested:
        raise Stopped(_stop_requested[0])


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
        batch_size, workers: as in :meth:`~evseg_torch.pipeline.CascadedSegmenter.stream`.
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


def segment_file(job: Job, progress: bool = False) -> dict:
    """Segment one recording window by window into its output folder (see :mod:`evseg_torch.app.output`).

    Args:
        job: the input and its options.
        progress: show a progress bar (with a total and an ETA where the window count is known).

    Returns:
        The run's summary (also ``summary.json``).

    Raises:
        EvsegError: bad input, or a folder that cannot be written or resumed as asked.
        Stopped: a signal stopped the run; its partial results stay to resume.
    """
    from tqdm.auto import tqdm

    from evseg_torch.app.output import SegmentationWriter
    from evseg_torch.io import iter_event_chunks
    from evseg_torch.pipeline import CascadedSegmenter

    started = time.perf_counter()
    segmenter = CascadedSegmenter(job.sensor_size, job.config).to(job.device)
    chunks = TimeRange(
        iter_event_chunks(job.path, job.chunk_size, sensor_size=job.sensor_size, topic=job.topic), job
    )
    writer = SegmentationWriter(
        job.out,
        job.config,
        run=job.identity(),
        save_images=job.save_images,
        overwrite=job.overwrite,
        resume=job.resume,
        video=job.video,
    )
    if writer.summary is not None:
        log.info("%s: already finished in %s", job.path.name, job.out)
        return writer.summary
    resume = writer.resume_point
    with writer, ExitStack() as stack:
        segment_windows = None
        if job.workers > 1:
            pool = stack.enter_context(WindowPool(segmenter, job.workers, batch_size=job.batch_size))
            segment_windows = pool.segment
        results = segmenter.stream(
            chunks,
            batch_size=job.batch_size,
            segment_windows=segment_windows,
            first_window=resume.next_window,
            max_windows=job.max_windows,
            initial_models=resume.models,
            initial_objects=resume.objects,
            next_object_id=resume.next_object_id,
        )
        bar = tqdm(
            total=_window_total(job),
            initial=resume.next_window,
            desc=job.path.name,
            unit=" windows",
            disable=not progress,
            delay=0.5,  # no bar for an input that fails at once
        )
        with bar:
            for result in results:
                writer.add(result, first_event=chunks.skipped)
                bar.update(result.window_index + 1 - bar.n)
                if writer.n_windows % job.batch_size == 0:
                    now = time.perf_counter()
                    writer.checkpoint(now - started)
                    started = now
                _raise_if_stopped()
            if bar.total:
                bar.update(bar.total - bar.n)  # the last windows may have been too sparse to segment
        if chunks.n_events == 0:
            raise EvsegError(f"{job.path}: no events {chunks.describe()}")
        extra = {
            "input": str(job.path),
            "sensor_size": list(job.sensor_size),
            "first_event": chunks.skipped,
        }
        n_events = None if job.max_windows is not None else chunks.n_events
        return writer.close(n_events, time.perf_counter() - started, extra)


def _window_total(job: Job) -> int | None:
    """How many windows the run cuts, where that is known without a pass over the events."""
    from evseg_torch.io import read_time_span

    window = job.config.window
    total = None
    if window.events_per_window is None:
        span = read_time_span(job.path)
        end_s = job.end_s
        if span is not None:
            length_s = 1e-6 * (span[1] - span[0])
            end_s = length_s if end_s is None else min(end_s, length_s)
        if end_s is not None:
            stride_ms = window.stride_ms or window.window_ms
            total = max(int(np.floor(1e3 * (end_s - (job.start_s or 0.0)) / stride_ms)) + 1, 0)
    if job.max_windows is not None:
        total = job.max_windows if total is None else min(total, job.max_windows)
    return total


class TimeRange:
    """Pass a recording's chunks through, keeping only the events of the job's time range.

    Attributes:
        skipped: events before the range (the index in the input of the first event kept).
        n_events: events kept so far.
    """

    def __init__(self, chunks, job: Job) -> None:
        self.chunks, self.start_s, self.end_s = chunks, job.start_s, job.end_s
        self.skipped = self.n_events = 0

    def __iter__(self) -> Iterator[np.ndarray]:
        first = start = end = None
        for chunk in self.chunks:
            if first is None:
                first = int(chunk["t"][0])
                start = first + round(1e6 * (self.start_s or 0.0))
                end = None if self.end_s is None else first + round(1e6 * self.end_s)
            begin = int(np.searchsorted(chunk["t"], start))
            stop = len(chunk) if end is None else int(np.searchsorted(chunk["t"], end))
            if self.n_events == 0:
                self.skipped += begin
            kept = chunk[begin:stop] if self.n_events == 0 else chunk[:stop]
            if len(kept):
                self.n_events += len(kept)
                yield kept
            if stop < len(chunk):
                return  # past the end: the rest of the recording is not read

    def describe(self) -> str:
        if self.start_s is None and self.end_s is None:
            return "in the recording"
        end = "the end" if self.end_s is None else f"{self.end_s:g} s"
        return f"between {self.start_s or 0:g} s and {end}"


def segment_files(jobs: Sequence[Job], workers: int = 1, keep_going: bool = False, progress: bool = False):
    """Segment several recordings, one after another or file by file in ``workers`` processes.

    On a Dask cluster, :func:`evseg_torch.app.cluster.segment_on_cluster` segments the same jobs, with the
    same results.

    Args:
        jobs: the inputs.
        workers: processes sharing out the files (one torch thread each); with one job its ``workers``
            field shares out windows instead.
        keep_going: report a bad input (one line) and go on with the others; otherwise stop at the first.
        progress: progress bars.

    Returns:
        One ``(job, summary or None, error message or None)`` per job, in order (with ``keep_going``,
        the failed ones have a message, already reported on standard error; without it the first failure
        is raised).

    Raises:
        EvsegError: a job failed and ``keep_going`` is off.
        Stopped: a signal stopped the run.
    """
    outcomes = []
    if workers <= 1 or len(jobs) == 1:
        for job in jobs:
            outcomes.append(_attempt(job, keep_going, progress))
        return outcomes
    from tqdm.auto import tqdm

    context = multiprocessing.get_context()
    pool = context.Pool(min(workers, len(jobs)), initializer=_file_worker)
    try:
        pending = [pool.apply_async(_attempt, (job, True, False)) for job in jobs]
        for task in tqdm(pending, desc="files", disable=not progress):
            while not task.ready():
                task.wait(0.2)
                _raise_if_stopped()
            outcome = task.get()
            if outcome[2] is not None and not keep_going:
                raise EvsegError(outcome[2])
            outcomes.append(outcome)
        pool.close()
    finally:
        pool.terminate()
        pool.join()
    return outcomes


def _attempt(job: Job, keep_going: bool, progress: bool):
    try:
        return job, segment_file(job, progress), None
    except (EvsegError, OSError) as err:
        if not keep_going:
            raise
        return job, None, failure(job.path, err)


def failure(path, err: BaseException) -> str:
    """Report an input that failed on standard error at once, as one line naming it; returns the line."""
    message = one_line(err)
    if str(path) not in message:
        message = f"{path}: {message}"
    print(f"evseg: error: {message}", file=sys.stderr, flush=True)
    return message


def _file_worker() -> None:
    from evseg_torch.app.threads import set_threads

    worker_signals()
    set_threads(1)


def with_window(config: SegmenterConfig, window_ms=None, stride_ms=None, events_per_window=None):
    """``config`` with the window geometry given on the command line (``None`` keeps the config's)."""
    if events_per_window is not None:
        return replace_config(config, events_per_window=events_per_window)
    overrides = {k: v for k, v in {"window_ms": window_ms, "stride_ms": stride_ms}.items() if v is not None}
    return replace_config(config, **overrides)


def one_line(err: BaseException) -> str:
    """An exception as one line of text."""
    return " ".join(str(err).split()) or type(err).__name__

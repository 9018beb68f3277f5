"""Segmenting recordings into result folders: what ``evseg segment`` does with its jobs.

* **Resumable**: results go to the folder's ``.partial/`` with a checkpoint after every batch of windows
  and are published when complete; a stopped run resumes from its checkpoint and ends with the files an
  uninterrupted run writes (windows after a checkpoint are segmented again, from the same models, and
  their object ids continue the last window's as they would have).
* **Stopping**: a signal stops the run at the next window at the latest (:mod:`evseg_torch.app.signals`);
  its partial results stay to resume.
* **Many inputs**: one after another, or file by file in worker processes (:func:`segment_files`); with
  ``keep_going`` a bad input is reported and the others are segmented. :mod:`evseg_torch.app.cluster`
  runs the same jobs as tasks on a Dask cluster, each by :func:`segment_file`.
"""

from __future__ import annotations

import logging
import multiprocessing
import time
from collections.abc import Iterator, Sequence
from contextlib import ExitStack

import numpy as np

from evseg_torch.app.jobs import Job, failure
from evseg_torch.app.signals import raise_if_stopped, worker_signals
from evseg_torch.app.workers import WindowPool
from evseg_torch.errors import EvsegError

log = logging.getLogger("evseg")


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
                raise_if_stopped()
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
                raise_if_stopped()
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


def _file_worker() -> None:
    from evseg_torch.app.threads import set_threads

    worker_signals()
    set_threads(1)

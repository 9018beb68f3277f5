"""Segmenting many recordings on a Dask cluster: one task per input, on as many machines as it has.

* **Tasks**: each input's :class:`~evseg_torch.app.jobs.Job` is one task that runs
  :func:`~evseg_torch.app.runs.segment_file` on a worker, with one torch thread, so its folder holds what a
  run on this machine writes (same files, same labels for the same config and seed). Workers read the
  inputs and write the outputs by the paths given here, made absolute: the same paths must name the same
  files on every machine (a shared filesystem), and every worker must import the same version of
  evseg_torch (checked before the tasks are sent).
* **Failures**: a bad input or a refused folder (an :class:`~evseg_torch.errors.EvsegError`) is final and
  comes back as a value. Anything else a task raises is retried :data:`RETRIES` times (``retries=`` of
  ``Client.submit``), and a task whose worker dies is rerun elsewhere by the scheduler (Dask's
  ``distributed.scheduler.allowed-failures``, 3 by default).
* **A retried task continues its own run**: a task counts its attempts on the scheduler (task metadata);
  a later attempt whose folder holds a stopped or finished run of this very job (same input, config and
  options, checked as ``--resume`` checks them) resumes it from its last checkpoint, or returns its
  summary, rather than being refused for it ("pass --resume") or starting again. A first attempt runs
  the job as given, so a run left by an earlier command is treated exactly as on one machine.
* **Stopping**: stopping the command cancels the tasks not yet started and, on a ``local:N`` cluster,
  ends its workers; on another cluster the tasks already running finish their input, since Dask cannot
  interrupt a running task.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import replace

from evseg_torch.app.jobs import Job, failure, one_line
from evseg_torch.app.runs import segment_file
from evseg_torch.errors import EvsegError
from evseg_torch.version import __version__

log = logging.getLogger("evseg")

RETRIES = 2
"""Times a task that raised something other than an EvsegError is tried again."""


@contextmanager
def connect(scheduler: str) -> Iterator:
    """A Dask ``Client`` for ``scheduler``, closed (with its cluster, if made here) at the end of the block.

    Args:
        scheduler: a scheduler's address (``tcp://host:8786``), or ``local:N`` for a ``LocalCluster``
            of N single-threaded worker processes on this machine.

    Raises:
        EvsegError: Dask is not installed, ``local:N`` has no valid N, or no scheduler answers.
    """
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise EvsegError("--scheduler needs Dask: pip install 'evseg-torch[dask]'") from None
    # Dask's lines about its own start and stop would bury ours.
    logging.getLogger("distributed").setLevel(logging.ERROR)
    cluster = None
    try:
        if scheduler.startswith("local:"):
            count = scheduler.removeprefix("local:")
            if not count.isdigit() or int(count) < 1:
                raise EvsegError(f"--scheduler {scheduler}: local:N needs N, the worker count, of at least 1")
            cluster = LocalCluster(
                n_workers=int(count),
                threads_per_worker=1,
                processes=True,
                dashboard_address=":0",  # any free port: two local clusters never clash
                env={"DASK_LOGGING__DISTRIBUTED": "error"},
            )
            client = Client(cluster)
        else:
            client = Client(scheduler, timeout="20s")
    except (OSError, ValueError, TypeError) as err:
        if cluster is not None:
            cluster.close()
        raise EvsegError(f"--scheduler {scheduler}: cannot connect ({one_line(err)})") from None
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def segment_on_cluster(client, jobs: Sequence[Job], keep_going: bool = False, progress: bool = False):
    """Segment each job as one task on ``client``'s cluster; see :func:`evseg_torch.app.runs.segment_files`.

    Args:
        client: a ``distributed.Client``.
        jobs: the inputs; each job's ``workers`` must be 1 (a task runs in one worker process).
        keep_going: report a failed input (one line) and go on; otherwise cancel the rest and raise.
        progress: a progress bar over the inputs.

    Returns:
        One ``(job, summary or None, error message or None)`` per job, in order.

    Raises:
        EvsegError: a job failed and ``keep_going`` is off, or the workers cannot run evseg_torch.
    """
    from distributed import as_completed
    from tqdm.auto import tqdm

    if any(job.workers > 1 for job in jobs):
        raise EvsegError("on a cluster each input runs in one worker process: a job's workers must be 1")
    if not jobs:
        return []
    _check_workers(client)
    run_id = uuid.uuid4().hex
    futures = {
        client.submit(
            _segment_task, _absolute(job), run_id, index, key=f"evseg-{run_id}-{index}", retries=RETRIES
        ): index
        for index, job in enumerate(jobs)
    }
    outcomes = [None] * len(jobs)
    try:
        done = as_completed(futures, with_results=True, raise_errors=False)
        for future, result in tqdm(done, total=len(futures), desc="files", disable=not progress):
            index = futures.pop(future)  # a result held by no future is never recomputed
            job = jobs[index]
            # An erred future's result is (type, exception, traceback), after its retries.
            summary, error = (None, _failed(job, result[1])) if future.status == "error" else result
            if error is not None and not keep_going:
                raise error
            outcomes[index] = (job, summary, None if error is None else failure(job.path, error))
    finally:
        client.cancel(list(futures))
        client.set_metadata(run_id, None)
    return outcomes


def _absolute(job: Job) -> Job:
    """``job`` with absolute paths: a worker elsewhere has another working directory."""
    return replace(job, path=job.path.absolute(), out=job.out.absolute())


def _failed(job: Job, err: BaseException) -> EvsegError:
    """A task's unexpected failure (after its retries) as one of our errors, naming the input."""
    return EvsegError(f"{job.path}: failed on the cluster: {type(err).__name__}: {one_line(err)}")


def _check_workers(client) -> None:
    """Refuse workers that run another evseg_torch, or none; warn of workers with several threads."""
    versions = client.run(_worker_version, on_error="return")
    for address, version in versions.items():
        if isinstance(version, BaseException):
            raise EvsegError(
                f"worker {address} cannot run evseg_torch ({type(version).__name__}: {one_line(version)}); "
                "install the package on every worker"
            )
        if version != __version__:
            raise EvsegError(f"worker {address} runs evseg_torch {version}, this machine {__version__}")
    threads = {info["nthreads"] for info in client.scheduler_info(n_workers=-1)["workers"].values()}
    if max(threads, default=1) > 1:
        log.warning(
            "evseg: some workers run %d threads: inputs then share one process, whose graph cuts hold the "
            "GIL; start workers with --nthreads 1 and --nworkers set to the cores",
            max(threads),
        )


def _worker_version() -> str:
    return __version__


def _segment_task(job: Job, run_id: str, index: int) -> tuple[dict | None, EvsegError | None]:
    """Run on a worker: segment one input; a bad input comes back as a value, so it is not retried."""
    from evseg_torch.app.output import holds_run
    from evseg_torch.app.threads import set_threads

    set_threads(1)
    if _attempt(run_id, index) > 1 and holds_run(job.out, job.identity()):
        job = replace(job, resume=True, overwrite=False)  # an earlier attempt of this task stopped
    try:
        return segment_file(job), None
    except EvsegError as err:
        return None, err


def _attempt(run_id: str, index: int) -> int:
    """This task's attempt number (1 for the first), counted on the scheduler."""
    from distributed import get_client

    client = get_client()
    key = [run_id, str(index)]
    attempt = client.get_metadata(key, default=0) + 1
    client.set_metadata(key, attempt)
    return attempt

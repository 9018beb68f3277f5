"""Segmenting on a Dask cluster (``evseg segment --scheduler``) writes what a run on one machine writes."""

import json
import signal
from dataclasses import replace

import numpy as np
import pytest

pytest.importorskip("distributed")

from evseg_torch.app import cluster, runs
from evseg_torch.app.cli import main
from evseg_torch.app.jobs import Job
from evseg_torch.app.output import OutputExistsError, folder_state
from evseg_torch.app.runs import segment_file
from evseg_torch.app.signals import Stopped
from evseg_torch.config import SegmenterConfig, replace_config
from evseg_torch.errors import EvsegError
from tests.helpers.cli import SIZE, scene_file


@pytest.fixture(scope="module")
def client():
    """A local cluster of 2 single-threaded worker processes, shared by this file's tests."""
    with cluster.connect("local:2") as client:
        yield client


def _written(folder):
    """A result folder's labels and its models.jsonl rows without the timings."""
    rows = [json.loads(line) for line in (folder / "models.jsonl").read_text().splitlines()]
    for row in rows:
        del row["timings_ms"]
    return np.load(folder / "labels.npz")["labels"], rows


@pytest.mark.slow
def test_cluster_run_equals_a_local_run_and_lists_a_bad_input(tmp_path, client, capsys):
    scenes = [scene_file(tmp_path, seed=seed) for seed in (0, 1)]
    backwards = tmp_path / "back.txt"
    backwards.write_text("0.002 1 1 1\n0.001 1 1 0\n")  # found bad only when a worker reads it
    args = ["--quiet", "segment", "--window-ms", "20", "--sensor-size", SIZE, "--keep-going"]
    assert main([*args, *map(str, scenes), "--out", str(tmp_path / "local")]) == 0
    capsys.readouterr()
    inputs = [str(scenes[0]), str(backwards), str(scenes[1])]
    address = client.scheduler.address
    assert main([*args, *inputs, "--out", str(tmp_path / "cluster"), "--scheduler", address]) == 1
    err = capsys.readouterr().err
    assert "1 of 3 inputs failed" in err and f"{backwards}: " in err and "decrease" in err
    assert f"{backwards}: {backwards}" not in err
    for scene in scenes:
        local, there = _written(tmp_path / "local" / scene.stem), _written(tmp_path / "cluster" / scene.stem)
        np.testing.assert_array_equal(local[0], there[0])
        assert local[1] == there[1] and len(local[1]) >= 2
    assert not (tmp_path / "cluster" / "back").exists()  # a bad input leaves no partial results


def test_without_keep_going_a_failure_stops_the_run(tmp_path, client):
    bad = tmp_path / "empty.txt"
    bad.write_text("# no events\n")
    job = Job(path=bad, out=tmp_path / "out" / "empty", sensor_size=(90, 120), config=SegmenterConfig())
    with pytest.raises(EvsegError, match="no events"):
        cluster.segment_on_cluster(client, [job])
    assert "no events" in cluster.segment_on_cluster(client, [job], keep_going=True)[0][2]


def test_an_unexpected_failure_is_retried_then_reported(tmp_path, client):
    (tmp_path / "file").write_text("")
    job = replace(_job(tmp_path), out=tmp_path / "file" / "out")  # not a folder: an OSError on every try
    with pytest.raises(EvsegError, match=r"failed on the cluster: \w*Error"):
        cluster.segment_on_cluster(client, [job])


def _job(tmp_path, **options):
    path = scene_file(tmp_path)
    config = replace_config(SegmenterConfig(), window_ms=10.0)
    return Job(path=path, out=tmp_path / "out" / path.stem, sensor_size=(90, 120), config=config, **options)


def _stop_after_first_window(monkeypatch):
    def stop():
        monkeypatch.undo()
        raise Stopped(signal.SIGTERM)

    monkeypatch.setattr(runs, "raise_if_stopped", stop)


def test_a_retried_task_continues_its_own_stopped_run(tmp_path, monkeypatch):
    job = _job(tmp_path)
    _stop_after_first_window(monkeypatch)
    with pytest.raises(Stopped):
        segment_file(job)
    assert folder_state(job.out) == "stopped"
    # A first attempt runs the job as given: a stopped run it finds is refused, as on one machine.
    monkeypatch.setattr(cluster, "_attempt", lambda run_id, index: 1)
    summary, error = cluster._segment_task(job, "run", 0)
    assert summary is None and isinstance(error, OutputExistsError) and "--resume" in str(error)
    # A retry (its worker died, or it raised) resumes it, and ends with an uninterrupted run's files.
    monkeypatch.setattr(cluster, "_attempt", lambda run_id, index: 2)
    summary, error = cluster._segment_task(job, "run", 0)
    assert error is None and summary["windows"] >= 3
    whole = _job(tmp_path / "whole")
    segment_file(whole)
    resumed, uninterrupted = _written(job.out), _written(whole.out)
    np.testing.assert_array_equal(resumed[0], uninterrupted[0])
    assert resumed[1] == uninterrupted[1]
    # A retry after the run was published (the result was lost with its worker) returns its summary.
    assert cluster._segment_task(job, "run", 0) == (summary, None)


def test_a_retry_does_not_resume_another_jobs_run(tmp_path, monkeypatch):
    job = _job(tmp_path)
    _stop_after_first_window(monkeypatch)
    with pytest.raises(Stopped):
        segment_file(job)
    monkeypatch.setattr(cluster, "_attempt", lambda run_id, index: 2)
    other = replace(job, config=replace_config(job.config, window_ms=15.0), overwrite=True)
    summary, error = cluster._segment_task(other, "run", 0)
    assert error is None and summary["run"]["config"]["window"]["window_ms"] == 15.0  # overwritten, as asked


def _die_at_the_second_window(marker):
    """In a worker: the first task to finish its second window ends the worker process, once."""
    import os

    original, windows = runs.raise_if_stopped, []

    def stop():
        windows.append(1)
        if len(windows) == 2 and not os.path.exists(marker):
            open(marker, "w").close()
            os._exit(1)  # as a killed or crashed machine would: no clean-up
        original()

    stop.original = original
    runs.raise_if_stopped = stop


def _live_on():
    runs.raise_if_stopped = getattr(runs.raise_if_stopped, "original", runs.raise_if_stopped)


def test_a_task_whose_worker_dies_resumes_on_another(tmp_path, client):
    job = _job(tmp_path)
    marker = tmp_path / "died"
    client.run(_die_at_the_second_window, str(marker))
    try:
        [(_, summary, error)] = cluster.segment_on_cluster(client, [job])
    finally:
        client.run(_live_on)
    assert marker.exists() and error is None
    whole = _job(tmp_path / "whole")
    segment_file(whole)
    resumed, uninterrupted = _written(job.out), _written(whole.out)
    np.testing.assert_array_equal(resumed[0], uninterrupted[0])
    assert resumed[1] == uninterrupted[1] and summary["windows"] == len(uninterrupted[1]) >= 3


@pytest.mark.parametrize(
    ("scheduler", "message"),
    [("local:0", "at least 1"), ("local:two", "at least 1")],
)
def test_bad_scheduler_gives_one_line(tmp_path, capsys, scheduler, message):
    path = scene_file(tmp_path)
    assert (
        main(["--quiet", "segment", str(path), "--out", str(tmp_path / "o"), "--scheduler", scheduler]) == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_workers_and_scheduler_exclude_each_other(tmp_path, capsys):
    path = scene_file(tmp_path)
    args = ["--quiet", "segment", str(path), "--out", str(tmp_path / "o"), "--workers", "2"]
    assert main([*args, "--scheduler", "local:2"]) == 2
    assert "--workers" in capsys.readouterr().err

"""``evseg segment`` as a batch tool: stopped and resumed runs, output folders, failures, options."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from evseg_torch.app.cli import main
from evseg_torch.app.jobs import output_folders
from evseg_torch.app.output import SegmentationWriter
from evseg_torch.config import SegmenterConfig
from evseg_torch.data import EventWindowDataset
from evseg_torch.errors import EventFormatError
from evseg_torch.events import EVENT_DTYPE, check_sensor_size
from evseg_torch.synthetic import make_scene

SIZE = (90, 120)
ROOT = Path(__file__).resolve().parents[2]


def _recording(path: Path, windows: int, events_per_window: int = 1500) -> Path:
    """A continuous recording of ``windows`` 30 ms synthetic scenes one after another, as text."""
    parts = []
    for window in range(windows):
        events = make_scene(SIZE, 0.03, 1 + window % 2, n_events=events_per_window, rng=window).events
        events["t"] = events["t"] - events["t"][0] + window * 30_000
        parts.append(events)
    events = np.concatenate(parts)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".npy":
        np.save(path, events)
    else:
        rows = np.column_stack([events["t"] * 1e-6, events["x"], events["y"], (events["p"] > 0).astype(int)])
        np.savetxt(path, rows, fmt=["%.6f", "%d", "%d", "%d"])
    return path


def _rows(folder: Path) -> list[dict]:
    """``models.jsonl`` without the timings, which no two runs share."""
    rows = [json.loads(line) for line in (folder / "models.jsonl").read_text().splitlines()]
    return [{k: v for k, v in row.items() if k != "timings_ms"} for row in rows]


def _segment(*args) -> int:
    return main(["--quiet", "segment", *map(str, args)])


def _last_error(capsys) -> str:
    return capsys.readouterr().err.strip().splitlines()[-1]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    return _recording(tmp_path_factory.mktemp("recording") / "rec.npy", windows=16)


@pytest.mark.slow
def test_killed_runs_resume_to_the_uninterrupted_files(recording, tmp_path):
    # SIGTERM and SIGINT alternately at random points of a run (starting up, segmenting, writing figures
    # and video frames), each time followed by --resume: the files at the end equal an uninterrupted run's.
    # The kill points are found by watching the figures appear, so they land mid-run on any machine.
    options = ["--sensor-size", "90x120", "--save-images", "--video"]
    assert _segment(recording, "--out", tmp_path / "full", *options) == 0
    command = [sys.executable, "-m", "evseg_torch.app.cli", "--quiet", "segment", str(recording)]
    command += ["--out", str(tmp_path / "part"), *options]
    environment = {**os.environ, "PYTHONPATH": str(ROOT)}
    rng = np.random.default_rng(0)
    folder = tmp_path / "part" / "rec"
    images = folder / ".partial" / "images"
    kills = 0
    for attempt in range(6):
        child = subprocess.Popen(
            [*command, *(["--resume"] if attempt else [])],
            env=environment,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        if attempt == 0:
            time.sleep(1.0)  # starting up
        else:
            target = (len(os.listdir(images)) if images.is_dir() else 0) + int(rng.integers(1, 3))
            deadline = time.monotonic() + 120
            while child.poll() is None and time.monotonic() < deadline:
                if images.is_dir() and len(os.listdir(images)) >= target:
                    break
                time.sleep(0.01)
            time.sleep(rng.uniform(0.0, 0.3))
        number = (signal.SIGTERM, signal.SIGINT)[attempt % 2]
        child.send_signal(number)
        _, err = child.communicate(timeout=120)
        if child.returncode == 0:
            break  # finished before the signal came
        kills += 1
        if child.returncode != -number:  # else killed while Python was still importing: nothing written
            assert child.returncode == 128 + number, err
            assert err.strip().splitlines()[-1].startswith(f"evseg: stopped by {number.name}"), err
        # Nothing partial is presented as a result.
        assert not (folder / "summary.json").exists() or not (folder / ".partial").exists()
    assert kills >= 5
    assert subprocess.run([*command, "--resume"], env=environment, timeout=300).returncode == 0
    full = tmp_path / "full" / "rec"
    assert (folder / "labels.npz").read_bytes() == (full / "labels.npz").read_bytes()
    assert _rows(folder) == _rows(full)
    assert sorted(p.name for p in (folder / "images").iterdir()) == sorted(
        p.name for p in (full / "images").iterdir()
    )
    summaries = [json.loads((f / "summary.json").read_text()) for f in (folder, full)]
    assert summaries[0]["video_frames"] == summaries[1]["video_frames"] == summaries[0]["windows"]
    assert not (folder / ".partial").exists()


def _stopped_run(tmp_path, recording) -> Path:
    """A run stopped after its first window's checkpoint, as a kill leaves it."""
    out = tmp_path / "out"
    assert _segment(recording, "--out", out, "--sensor-size", "90x120", "--max-windows", "1") == 0
    folder = out / "rec"
    finished = json.loads((folder / "summary.json").read_text())
    (folder / "summary.json").unlink()
    writer = SegmentationWriter(folder / "x", SegmenterConfig(), run={})
    writer.run = finished["run"]
    writer.run["options"]["max_windows"] = None
    writer.checkpoint()
    writer._close_files()
    for name in os.listdir(folder):
        if name != "x":
            os.remove(folder / name)
    os.rename(folder / "x" / ".partial", folder / ".partial")
    os.rmdir(folder / "x")
    return out


def test_resume_refuses_changed_runs_and_re_runs_say_what_to_do(recording, tmp_path, capsys):
    out = _stopped_run(tmp_path, recording)
    assert _segment(recording, "--out", out, "--sensor-size", "90x120") == 2
    assert "holds a stopped run; pass --resume to continue it or --overwrite" in _last_error(capsys)
    assert _segment(recording, "--out", out, "--sensor-size", "90x120", "--resume", "--window-ms", "20") == 2
    assert "config.window.window_ms differs (30.0 then, 20.0 now)" in _last_error(capsys)
    assert _segment(recording, "--out", out, "--sensor-size", "90x120", "--resume") == 0
    assert _segment(recording, "--out", out, "--sensor-size", "90x120") == 2
    assert "holds finished results; pass --overwrite" in _last_error(capsys)
    assert _segment(recording, "--out", out, "--sensor-size", "90x120", "--resume") == 0  # skips it
    assert _segment(recording, "--out", out, "--sensor-size", "90x120", "--resume", "--max-windows", "3") == 2
    assert "holds finished results, but options.max_windows differs (null then, 3 now)" in _last_error(capsys)


def test_inputs_with_one_stem_get_their_own_folders(tmp_path, capsys):
    first = _recording(tmp_path / "a" / "x" / "events.txt", windows=2)
    second = _recording(tmp_path / "b" / "y" / "events.txt", windows=3)
    out = tmp_path / "out"
    assert _segment(first, second, "--out", out, "--sensor-size", "90x120") == 0
    for name, path in (("x-events", first), ("y-events", second)):
        summary = json.loads((out / name / "summary.json").read_text())
        assert summary["input"] == str(path) and summary["windows"] >= 2
    # Another input with the stem of a finished one never replaces its results, even with --overwrite.
    assert _segment(first, "--out", tmp_path / "alone", "--sensor-size", "90x120") == 0
    assert _segment(second, "--out", tmp_path / "alone", "--sensor-size", "90x120", "--overwrite") == 2
    assert f"holds the results of {first.resolve()}" in _last_error(capsys)
    assert json.loads((tmp_path / "alone" / "events" / "summary.json").read_text())["input"] == str(first)


def test_output_folder_names():
    folders = output_folders(["d/a/x/e.txt", "d/b/x/e.txt", "d/c/e.npy", "f.txt"], "out")
    assert [folder.name for folder in folders] == ["a-x-e", "b-x-e", "c-e", "f"]


def test_keep_going_segments_the_good_inputs(tmp_path, capsys):
    good = _recording(tmp_path / "good.txt", windows=2)
    bad = tmp_path / "bad.txt"
    bad.write_text("0.0 1 1 1\nnot an event\n")
    other = _recording(tmp_path / "other.npy", windows=2)
    out = tmp_path / "out"
    assert _segment(good, bad, other, "--out", out, "--sensor-size", "90x120", "--keep-going") == 1
    err = capsys.readouterr().err
    assert "evseg: 1 of 3 inputs failed:" in err and f"{bad}" in err.splitlines()[-1]
    assert (out / "good" / "summary.json").is_file() and (out / "other" / "summary.json").is_file()
    assert not (out / "bad").exists()
    assert _segment(good, bad, "--out", tmp_path / "strict", "--sensor-size", "90x120") == 2


def test_sensor_size_one_rule(tmp_path, capsys):
    events = make_scene(SIZE, 0.03, 1, n_events=800, rng=0).events
    stored = tmp_path / "stored.npz"
    np.savez(stored, t_us=events["t"], x=events["x"], y=events["y"], p=events["p"], height=90, width=120)
    assert _segment(stored, "--out", tmp_path / "o1", "--sensor-size", "90x130") == 2
    assert "stores a 90x120 sensor but 90x130 was given" in _last_error(capsys)
    assert _segment(stored, "--out", tmp_path / "o2", "--sensor-size", "90x120") == 0
    with pytest.raises(EventFormatError, match="stores a 90x120 sensor"):
        EventWindowDataset(stored, window_ms=10, sensor_size=(90, 130))
    # No stored size and none given: the smallest that holds the events, in the CLI and the dataset alike.
    plain = tmp_path / "plain.npy"
    np.save(plain, events)
    assert _segment(plain, "--out", tmp_path / "o3") == 0
    inferred = json.loads((tmp_path / "o3" / "plain" / "summary.json").read_text())["sensor_size"]
    assert inferred == list(EventWindowDataset(plain, window_ms=10).sensor_size)
    assert inferred == [int(events["y"].max()) + 1, int(events["x"].max()) + 1]


def test_sensor_sizes_are_whole_numbers():
    assert check_sensor_size((np.float64(180.0), 240)) == (180, 240)
    for bad in ((180.7, 240), (True, 240), ("180", 240)):
        with pytest.raises(EventFormatError, match="whole numbers"):
            check_sensor_size(bad)


def test_workers_alone_do_not_change_results(recording, tmp_path, caplog):
    written = {}
    for workers in (1, 2):
        out = tmp_path / f"w{workers}"
        assert main(["segment", str(recording), "--out", str(out), "--workers", str(workers)]) == 0
        written[workers] = np.load(out / "rec" / "labels.npz")["labels"]
    np.testing.assert_array_equal(written[1], written[2])
    assert "--workers 2 has nothing to share with --batch-size 1" in caplog.text


def test_time_range_and_window_limit(recording, tmp_path):
    all_events = np.load(recording)
    assert _segment(recording, "--out", tmp_path / "r", "--start", "0.1", "--end", "0.25") == 0
    summary = json.loads((tmp_path / "r" / "rec" / "summary.json").read_text())
    t = (all_events["t"] - all_events["t"][0]) * 1e-6
    inside = np.flatnonzero((t >= 0.1) & (t < 0.25))
    assert summary["first_event"] == inside[0] and summary["events"] == len(inside)
    assert summary["windows"] == 5
    labels = np.load(tmp_path / "r" / "rec" / "labels.npz")["labels"]
    assert labels.shape == (len(inside),) and labels.min() >= 0
    assert _segment(recording, "--out", tmp_path / "m", "--max-windows", "2") == 0
    assert json.loads((tmp_path / "m" / "rec" / "summary.json").read_text())["windows"] == 2


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--events-per-window", "500", "--stride-ms", "5"], "--stride-ms applies to time windows"),
        (["--start", "0.2", "--end", "0.1"], "--end (0.1 s) must come after --start (0.2 s)"),
        (["--max-windows", "0"], "--max-windows must be at least 1"),
        (["--start", "-1"], "--start must be a number of seconds of at least 0"),
        (["--device", "nonsense"], "--device nonsense: not a torch device name"),
    ],
)
def test_option_errors_are_one_line(recording, tmp_path, capsys, args, message):
    assert _segment(recording, "--out", tmp_path / "o", *args) == 2
    assert message in _last_error(capsys)
    assert not (tmp_path / "o").exists()


def test_input_errors_are_one_line(tmp_path, capsys):
    assert _segment(tmp_path, "--out", tmp_path / "o") == 2
    assert f"{tmp_path}: a folder of no known layout" in _last_error(capsys)
    empty = tmp_path / "empty.npy"
    np.save(empty, np.zeros(0, dtype=EVENT_DTYPE))
    assert _segment(empty, "--out", tmp_path / "o", "--sensor-size", "90x120") == 2
    assert "no events" in _last_error(capsys)


def test_cuda_device_is_a_clear_error_without_cuda(recording, tmp_path, capsys):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    assert _segment(recording, "--out", tmp_path / "o", "--device", "cuda") == 2
    error = _last_error(capsys)
    assert "--device cuda: this torch" in error and "sees no CUDA device" in error
    assert _segment(recording, "--out", tmp_path / "c", "--device", "cpu", "--max-windows", "1") == 0


def test_common_options_after_the_command_and_version(recording, tmp_path, capsys):
    assert (
        main(["segment", str(recording), "--out", str(tmp_path / "o"), "--max-windows", "1", "--quiet"]) == 0
    )
    assert capsys.readouterr().err == ""
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0 and capsys.readouterr().out.startswith("evseg ")


def test_a_stop_inside_an_import_is_a_stop():
    """A signal inside an import that wraps its errors (scipy's) comes out as an ImportError caused by
    our Stopped; stopped_by finds it, so that the CLI reports the stop (exit 143), not a traceback."""
    from evseg_torch.app.signals import Stopped, stopped_by

    try:
        try:
            raise Stopped(signal.SIGTERM)
        except Stopped as stop:
            raise ImportError("initialization failed") from stop
    except ImportError as err:
        assert stopped_by(err).signum == signal.SIGTERM
    assert stopped_by(ValueError("not a stop")) is None


def test_an_rpg_sequence_folder_is_segmented_under_its_name(tmp_path):
    """``evseg segment`` on an rpg / ECD / EED folder: events.txt read, the frames' size used."""
    folder = tmp_path / "sequence"
    _recording(folder / "events.txt", windows=2)
    (folder / "images").mkdir()
    cv2.imwrite(str(folder / "images" / "frame_0.png"), np.zeros(SIZE, np.uint8))
    (folder / "images.txt").write_text("0.0 images/frame_0.png\n")
    assert _segment(folder, "--out", tmp_path / "out") == 0
    summary = json.loads((tmp_path / "out" / "sequence" / "summary.json").read_text())
    assert summary["windows"] == 2 and summary["sensor_size"] == list(SIZE)

"""``evseg segment``: result folders, batches, workers, and one line for each bad input."""

import json
import zipfile

import numpy as np
import pytest
import yaml

from evseg_torch.app.cli import main
from evseg_torch.io import load_events
from tests.helpers.cli import SIZE, error_line, scene_file, text_file


def test_segment_writes_results_in_input_order(tmp_path):
    path = scene_file(tmp_path)
    out = tmp_path / "out"
    code = main(["--quiet", "segment", str(path), "--out", str(out), "--window-ms", "20", "--save-images"])
    assert code == 0
    folder = out / path.stem
    labels = np.load(folder / "labels.npz")
    n_events = len(load_events(path))
    assert labels["labels"].shape == labels["window"].shape == (n_events,)
    assert labels["labels"].dtype == np.int64
    windows = [json.loads(line) for line in (folder / "models.jsonl").read_text().splitlines()]
    assert [w["window"] for w in windows] == list(range(len(windows))) and len(windows) >= 2
    for w in windows:
        chunk = labels["labels"][w["first_event"] : w["first_event"] + w["n_events"]]
        assert chunk.min() >= 0 and chunk.max() < len(w["models"])
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["events"] == n_events and summary["windows"] == len(windows)
    assert set(summary["timings_ms"]) == {"features", "level_one", "level_two", "total"}
    assert (folder / "config.yaml").is_file()
    assert len(list((folder / "images").glob("*.png"))) == len(windows)


def test_config_by_bundled_name_or_file(tmp_path, monkeypatch, capsys):
    path = scene_file(tmp_path)
    args = ["--quiet", "segment", str(path), "--window-ms", "20", "--max-windows", "1"]
    monkeypatch.chdir(tmp_path)
    assert main([*args, "--out", "named", "--config", "fast"]) == 0
    written = yaml.safe_load((tmp_path / "named" / path.stem / "config.yaml").read_text())
    assert written["level_two"]["discovery_rounds"] == 0
    # A file of that name is the config, not the bundled one.
    (tmp_path / "fast").write_text("level_two:\n  lambda_smooth: 12\n")
    assert main([*args, "--out", "file", "--config", "fast"]) == 0
    written = yaml.safe_load((tmp_path / "file" / path.stem / "config.yaml").read_text())
    assert written["level_two"]["lambda_smooth"] == 12 and written["level_two"]["discovery_rounds"] == 2
    capsys.readouterr()
    assert main([*args, "--out", "none", "--config", "fastest"]) == 2
    assert "fastest" in capsys.readouterr().err


def test_segment_in_batches_writes_the_same_windows(tmp_path, capsys):
    path = scene_file(tmp_path)
    written = {}
    for batch_size in (1, 3):
        out = tmp_path / f"out{batch_size}"
        args = ["--quiet", "segment", str(path), "--out", str(out), "--window-ms", "10"]
        assert main([*args, "--batch-size", str(batch_size)]) == 0
        lines = (out / path.stem / "models.jsonl").read_text().splitlines()
        written[batch_size] = [(w["window"], w["first_event"], w["n_events"]) for w in map(json.loads, lines)]
    assert written[1] == written[3] and len(written[1]) >= 3
    assert main(["--quiet", "segment", str(path), "--out", str(tmp_path / "x"), "--batch-size", "0"]) == 2
    assert "--batch-size" in error_line(capsys)


def test_existing_output_needs_overwrite(tmp_path, capsys):
    path = scene_file(tmp_path)
    out = tmp_path / "out"
    (out / path.stem).mkdir(parents=True)
    (out / path.stem / "keep.txt").write_text("mine")
    assert main(["--quiet", "segment", str(path), "--out", str(out)]) == 2
    assert "--overwrite" in error_line(capsys)
    assert (out / path.stem / "keep.txt").read_text() == "mine"
    assert main(["--quiet", "segment", str(path), "--out", str(out), "--overwrite", "--window-ms", "40"]) == 0
    assert not (out / path.stem / "keep.txt").exists()


def _truncated_npz(tmp_path):
    path = tmp_path / "cut.npz"
    np.savez(path, events=np.zeros((100, 4)))
    path.write_bytes(path.read_bytes()[:60])
    return path


def _garbled_npz(tmp_path):
    path = tmp_path / "bad.npz"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("events.npy", b"not an array")
    return path


@pytest.mark.parametrize(
    ("make", "args", "message"),
    [
        (lambda p: p / "missing.txt", ["--sensor-size", SIZE], "no such file"),
        (
            lambda p: text_file(p, "events.xyz", ["0 1 1 1"]),
            ["--sensor-size", SIZE],
            "unknown event file suffix",
        ),
        (_truncated_npz, ["--sensor-size", SIZE], "cut.npz"),
        (_garbled_npz, ["--sensor-size", SIZE], "bad.npz"),
        (lambda p: text_file(p, "far.txt", ["0.0 500 1 1"]), ["--sensor-size", SIZE], "outside the sensor"),
        (
            lambda p: text_file(p, "back.txt", ["0.002 1 1 1", "0.001 1 1 0"]),
            ["--sensor-size", SIZE],
            "decrease",
        ),
        (lambda p: text_file(p, "empty.txt", ["# no events"]), ["--sensor-size", SIZE], "no events"),
        (
            lambda p: text_file(p, "ok.txt", ["0.0 1 1 1"]),
            ["--sensor-size", SIZE, "--events-per-window", "0"],
            "at least 1",
        ),
        (
            lambda p: text_file(p, "ok2.txt", ["0.0 1 1 1"]),
            ["--sensor-size", SIZE, "--window-ms", "-5"],
            "positive",
        ),
    ],
)
def test_bad_input_gives_one_line_and_exit_2(tmp_path, capsys, make, args, message):
    path = make(tmp_path)
    assert main(["--quiet", "segment", str(path), "--out", str(tmp_path / "out"), *args]) == 2
    assert message in error_line(capsys)


def test_workers_segment_files_in_parallel(tmp_path):
    first, second = scene_file(tmp_path, seed=0), scene_file(tmp_path, seed=1)
    out = tmp_path / "out"
    args = [
        "--quiet",
        "segment",
        str(first),
        str(second),
        "--out",
        str(out),
        "--workers",
        "2",
        "--window-ms",
        "40",
    ]
    assert main(args) == 0
    for path in (first, second):
        labels = np.load(out / path.stem / "labels.npz")["labels"]
        assert labels.shape == (len(load_events(path)),) and labels.max() >= 0


def test_workers_share_out_the_windows_of_one_file(tmp_path, capsys):
    path = scene_file(tmp_path)
    written = {}
    for workers in (1, 2):
        out = tmp_path / f"out{workers}"
        args = ["--quiet", "--threads", "1", "segment", str(path), "--out", str(out), "--window-ms", "10"]
        assert main([*args, "--batch-size", "2", "--workers", str(workers)]) == 0
        written[workers] = np.load(out / path.stem / "labels.npz")["labels"]
    np.testing.assert_array_equal(written[1], written[2])
    assert main(["--quiet", "segment", str(path), "--out", str(tmp_path / "x"), "--workers", "0"]) == 2
    assert "--workers" in error_line(capsys)

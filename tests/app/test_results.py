"""Result folders: the documented schema (docs/output_files.md) against the files written, load_results,
the video."""

import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from evseg_torch import load_results
from evseg_torch.app.cli import main
from evseg_torch.config import load_config
from evseg_torch.errors import ResultsError
from evseg_torch.motion import MOTION_MODELS
from evseg_torch.viz.render import PALETTE

README = Path(__file__).resolve().parents[2] / "README.md"
SCHEMA = README.parent / "docs" / "output_files.md"


def documented_fields() -> dict[str, set[str]]:
    """File -> field names of the schema's table (backticked names in the field column)."""
    section = SCHEMA.read_text()
    fields: dict[str, set[str]] = {}
    for line in section.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) == 5 and cells[0].startswith("`"):
            name = re.findall(r"`([^`]+)`", cells[0])[0]
            fields.setdefault(name, set()).update(re.findall(r"`([^`]+)`", cells[1]))
    return fields


@pytest.fixture(scope="module")
def result_folder(tmp_path_factory):
    pytest.importorskip("av")
    root = tmp_path_factory.mktemp("results")
    simulate = ["--quiet", "simulate", "--out", str(root), "--seeds", "0", "--sensor-size", "90x120"]
    assert main([*simulate, "--duration-ms", "40", "--objects", "1"]) == 0
    scene = root / "scene_0000.npz"
    segment = ["--quiet", "segment", str(scene), "--out", str(root / "out"), "--window-ms", "10"]
    assert main([*segment, "--save-images", "--video"]) == 0
    return root / "out" / "scene_0000"


def test_schema_documents_every_field_written(result_folder):
    documented = documented_fields()
    with np.load(result_folder / "labels.npz") as data:
        assert set(data.files) == documented["labels.npz"]
    for line in (result_folder / "models.jsonl").read_text().splitlines():
        assert set(json.loads(line)) == documented["models.jsonl"]
    assert set(json.loads((result_folder / "summary.json").read_text())) == documented["summary.json"]
    import yaml

    assert set(yaml.safe_load((result_folder / "config.yaml").read_text())) == documented["config.yaml"]
    assert {"images/NNNNNN.png", "video.mp4"} <= set(documented)


def test_schema_documents_the_demo_metrics(tmp_path):
    assert main(["--quiet", "demo", "--out", str(tmp_path)]) == 0
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert set(metrics) == documented_fields()["metrics.json"]
    assert all(isinstance(value, int | float) for key, value in metrics.items() if key != "timings_ms")


def test_schema_documents_each_motion_models_parameters():
    text = SCHEMA.read_text()
    for name, model in MOTION_MODELS.items():
        row = next(line for line in text.splitlines() if line.startswith(f"| `{name}`"))
        assert re.findall(r"`([^`]+)`", row.split("|")[2]) == list(model.param_names)
        assert [unit.strip() for unit in row.split("|")[3].split(",")] == list(model.param_units)


def test_load_results_round_trip(result_folder):
    results = load_results(result_folder)
    with np.load(result_folder / "labels.npz") as data:
        np.testing.assert_array_equal(results.labels, data["labels"])
        np.testing.assert_array_equal(results.window, data["window"])
    assert results.summary["windows"] == len(results.windows) == len(results.images) >= 3
    assert results.config == load_config(result_folder / "config.yaml")
    for record in results.windows:
        model = MOTION_MODELS[record.motion_model]
        assert record.parameters == model.param_names and record.units == model.param_units
        assert record.models.shape[1] == len(model.param_names)
        chunk = results.labels[record.first_event : record.first_event + record.n_events]
        assert chunk.min() >= 0 and chunk.max() < len(record.models)
        assert record.t_first_us <= record.t_last_us
        n_clusters = len(record.models)
        assert record.object_ids.shape == record.shared_motion.shape == (n_clusters,)
        assert record.centres.shape == (n_clusters, 2) and record.boxes.shape == (n_clusters, 4)
    ids = [set(record.object_ids.tolist()) for record in results.windows]
    assert all(0 in window for window in ids)  # the background, in every window of this scene
    assert results.video == result_folder / "video.mp4"
    with pytest.raises(AttributeError):
        results.labels = None  # frozen


def test_video_has_one_frame_per_window(result_folder):
    from evseg_torch.viz.video import read_frames

    frames = read_frames(result_folder / "video.mp4")
    n_windows = len(load_results(result_folder).windows)
    assert (
        len(frames) == n_windows == json.loads((result_folder / "summary.json").read_text())["video_frames"]
    )
    for frame in frames:
        # Every window has a cluster 0, drawn in its colour (H.264 is lossy: nearly that colour).
        distance = np.abs(frame.astype(int) - PALETTE[0].astype(int)).sum(axis=2)
        assert (distance < 40).sum() > 20


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda folder: (folder / "summary.json").unlink(), "no summary.json"),
        (lambda folder: (folder / "summary.json").write_text('{"schema_version": 99}'), "newer"),
        (lambda folder: (folder / "summary.json").write_text("{}"), "no schema_version"),
        (lambda folder: (folder / "summary.json").write_text("[1"), "not valid JSON"),
        (lambda folder: (folder / "labels.npz").write_bytes(b"junk"), "labels.npz"),
    ],
)
def test_load_results_refuses_what_is_not_a_result(tmp_path, result_folder, damage, message):
    import shutil

    copy = shutil.copytree(result_folder, tmp_path / "copy")
    damage(copy)
    with pytest.raises(ResultsError, match=message) as error:
        load_results(copy)
    assert "\n" not in str(error.value)
    with pytest.raises(ResultsError, match="does not exist"):
        load_results(tmp_path / "missing")


def test_readme_loading_example_runs(result_folder, tmp_path, monkeypatch, capsys):
    import shutil

    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.DOTALL)
    example = next(block for block in blocks if "load_results" in block)
    shutil.copytree(result_folder, tmp_path / "out" / "recording")
    monkeypatch.chdir(tmp_path)
    exec(compile(example, "README.md", "exec"), {})
    assert "affine4" in capsys.readouterr().out


def test_video_without_pyav_is_one_line_and_writes_nothing(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "av", None)  # as if the video extra were not installed
    events = tmp_path / "events.txt"
    events.write_text("0.0 1 1 1\n0.001 2 2 0\n")
    out = tmp_path / "out"
    assert (
        main(["--quiet", "segment", str(events), "--sensor-size", "90x120", "--out", str(out), "--video"])
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "evseg-torch[video]" in err[0]
    assert not (out / "events").exists()

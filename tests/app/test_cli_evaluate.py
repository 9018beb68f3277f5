"""``evseg evaluate``: the synthetic, EED and labelled protocols, and other methods' predictions."""

import json
from pathlib import Path

import numpy as np
import pytest

from evseg_torch.app.cli import main
from evseg_torch.evaluation.labelled import load_labelled, score_labelling
from evseg_torch.pipeline import CascadedSegmenter
from evseg_torch.synthetic import make_scene
from tests.helpers.cli import error_line, text_file


def test_evaluate_eed_on_a_real_sequence(real_data, tmp_path, capsys):
    """The EED protocol end to end on eed_occlusions (13 boxes), with its table, JSON and figure."""
    out = tmp_path / "eed.json"
    code = main(
        [
            "--quiet",
            "evaluate",
            "eed",
            str(real_data / "eed_occlusions"),
            "--json",
            str(out),
            "--figures",
            str(tmp_path / "figures"),
        ]
    )
    assert code == 0
    table = capsys.readouterr().out
    assert "occlusions" in table and "IROS21" in table
    row = json.loads(out.read_text())["occlusions"]
    assert row["boxes"] == row["evaluable"] == 13
    assert row["paper"]["IROS 2021"] == 100.0
    # Measured: IoU > 0.5 in 1 window, nested in 5 of 13, mean IoU 0.19.
    assert row["detection_rate_nested"] >= 100 * 4 / 13 and row["mean_iou"] > 0.15
    assert row["detection_rate_nested"] >= row["detection_rate"]
    assert (tmp_path / "figures" / "occlusions.png").stat().st_size > 10_000
    assert row["reference"] == "box"
    # Why each box was missed, and level one's part (measured: 5 background, 2 stretched; tracks on 12).
    assert "missed boxes (nested reading) by reason" in table
    missed = sum(row[f"missed_{reason}"] for reason in ("background", "merged", "stretched", "unassigned"))
    assert missed == round(13 * (1 - row["detection_rate_nested"] / 100))
    assert 0 <= row["boxes_with_own_model"] <= row["boxes_with_tracks"] <= 13


def test_evaluate_synthetic_over_pipeline_seeds(tmp_path, capsys):
    out = tmp_path / "synthetic.json"
    code = main(
        ["--quiet", "evaluate", "synthetic", "--seeds", "1", "--pipeline-seeds", "0-1", "--json", str(out)]
    )
    assert code == 0
    table = capsys.readouterr().out
    rows = [line.split() for line in table.splitlines() if line.split()[:1] in (["0"], ["1"])]
    assert [row[:2] for row in rows] == [["0", "1"], ["1", "1"]]  # pipeline seed, scene seed
    result = json.loads(out.read_text())
    assert sorted(result["runs"]) == ["0", "1"] and result["summary"]["scenes"] == 2
    assert all(run[0]["accuracy"] > 0.8 for run in result["runs"].values())


def test_evaluate_synthetic_family(tmp_path, capsys):
    out = tmp_path / "hard.json"
    assert (
        main(["--quiet", "evaluate", "synthetic", "--family", "hard", "--seeds", "2", "--json", str(out)])
        == 0
    )
    rows = [line.split() for line in capsys.readouterr().out.splitlines()]
    assert rows[0][-1] == "kinds" and rows[1][:2] == ["0", "2"] and rows[1][-1] == "small_fast"
    summary = json.loads(out.read_text())["summary"]
    assert rows[2][0] == "mean" and float(rows[2][1]) == round(summary["accuracy"], 3)
    assert rows[3][0] == "p10" and float(rows[3][2]) == round(summary["iou_p10"], 3)
    assert summary["scenes"] == 1 and summary["iou_p10"] == summary["iou"]


def _labelled_file(tmp_path, seed, n_objects):
    """A scene of ``evseg_torch.synthetic`` in the layout of ``shared/data/synthetic_probe``."""
    scene = make_scene((90, 120), duration=0.03, n_objects=n_objects, rng=seed)
    path = tmp_path / f"probe_{seed}.npz"
    np.savez(
        path,
        t_us=scene.events["t"],
        x=scene.events["x"].astype(np.int16),
        y=scene.events["y"].astype(np.int16),
        p=scene.events["p"].astype(np.int8),
        label=scene.labels.astype(np.int8),
        ambiguous=scene.ambiguous,
        sensor_size=np.array(scene.sensor_size, dtype=np.int32),
    )
    return path


def test_evaluate_labelled(tmp_path, capsys):
    paths = [_labelled_file(tmp_path, 0, 1), _labelled_file(tmp_path, 1, 2)]
    out = tmp_path / "labelled.json"
    assert main(["--quiet", "evaluate", "labelled", *map(str, paths), "--json", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    result = json.loads(out.read_text())
    files = result["files"]
    assert [f["name"] for f in files] == ["probe_0", "probe_1"] == [line.split()[0] for line in lines[1:3]]
    assert [f["n_events"] for f in files] == [len(np.load(p)["label"]) for p in paths]
    assert [f["n_objects"] for f in files] == [1, 2]
    for path, scored in zip(paths, files, strict=True):
        events, labels, ambiguous, size = load_labelled(path)
        xy = np.column_stack([events["x"], events["y"]])
        expected = score_labelling(CascadedSegmenter(size)(events).labels, labels, xy, ignore=ambiguous)
        for key in ("accuracy", "iou", "detection", "count_error"):
            assert scored[key] == getattr(expected, key)
        assert tuple(scored["outcomes"]) == expected.outcomes
    summary = result["summary"]
    assert summary["scenes"] == 2
    assert summary["accuracy"] == pytest.approx(np.mean([f["accuracy"] for f in files]))
    assert summary["abs_count_error"] == np.mean([abs(f["count_error"]) for f in files])
    assert lines[0].split()[:3] == ["file", "method", "events"]
    assert [line.split()[1] for line in lines[1:4]] == ["evseg"] * 3 and result["method"] == "evseg"
    assert lines[3].split()[0] == "mean" and float(lines[3].split()[4]) == round(summary["accuracy"], 3)
    assert lines[4].startswith(f"mean: accuracy {summary['accuracy']:.3f}, IMO IoU {summary['iou']:.3f}")


def _labels_renamed(tmp_path):
    path = _labelled_file(tmp_path, 0, 1)
    data = dict(np.load(path))
    np.savez(path, **{("labels" if k == "label" else k): v for k, v in data.items()})
    return path


def _labels_cut(tmp_path):
    path = _labelled_file(tmp_path, 0, 1)
    data = dict(np.load(path))
    np.savez(path, **{**data, "label": data["label"][:-1]})
    return path


@pytest.mark.parametrize(
    ("make", "args", "message"),
    [
        (lambda p: p / "missing.npz", [], "no such file"),
        (_labels_renamed, [], "no per-event label field 'label'"),
        (_labels_cut, [], "one integer label per event"),
        (_labels_renamed, ["--label-field", "sensor_size"], "one integer label per event"),
        (lambda p: _labelled_file(p, 0, 1), ["--sensor-size", "50x50"], "outside the sensor"),
        (lambda p: _labelled_file(p, 0, 1), ["--ignore-field", "sensor_size"], "one flag per event"),
        (lambda p: text_file(p, "events.txt", ["0.0 1 1 1"]), [], "must be an .npz file"),
    ],
)
def test_evaluate_labelled_bad_input(tmp_path, capsys, make, args, message):
    assert main(["--quiet", "evaluate", "labelled", str(make(tmp_path)), *args]) == 2
    assert message in error_line(capsys)


PROBE = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "synthetic_probe"


def _truth_as_predictions(folder, paths):
    """Each labelled file's own labels, written as ``folder/<stem>.npy``."""
    folder.mkdir(exist_ok=True)
    for path in paths:
        np.save(folder / f"{path.stem}.npy", np.load(path)["label"])
    return folder


@pytest.mark.skipif(not PROBE.is_dir(), reason="../shared/data/synthetic_probe is not beside the repository")
def test_evaluate_labelled_predictions(tmp_path, capsys):
    paths = [PROBE / "scene_200.npz", PROBE / "scene_205.npz"]
    folder = _truth_as_predictions(tmp_path / "truth", paths)
    out = tmp_path / "scores.json"
    command = ["--quiet", "evaluate", "labelled", *map(str, paths), "--predictions"]
    assert main([*command, str(folder), "--json", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == [
        "file",
        "method",
        "events",
        "IMOs",
        "accuracy",
        "IoU",
        "detect",
        "count",
        "ms",
    ]
    assert [line.split()[:2] for line in lines[1:4]] == [
        ["scene_200", "truth"],
        ["scene_205", "truth"],
        ["mean", "truth"],
    ]
    assert lines[3].split()[4:] == ["1.000", "1.000", "1.00", "+0.00", "-"]
    assert (
        lines[4]
        == "mean: accuracy 1.000, IMO IoU 1.000, detection 1.000, cluster-count error +0.00 (|.| 0.00)"
    )
    assert lines[5] == "missed objects: 0"
    result = json.loads(out.read_text())
    assert result["method"] == "truth" and result["summary"]["scenes"] == 2
    assert [(f["name"], f["method"], f["accuracy"], f["iou"]) for f in result["files"]] == [
        ("scene_200", "truth", 1.0, 1.0),
        ("scene_205", "truth", 1.0, 1.0),
    ]
    # The same predictions given one per FILE, in order, under another name.
    in_order = [str(folder / f"{path.stem}.npy") for path in paths]
    assert main([*command, *in_order, "--method", "EV-IMO net"]) == 0
    assert capsys.readouterr().out.splitlines()[3].startswith(f"{'mean':<20} EV-IMO net ")


@pytest.mark.parametrize(
    ("fields", "args", "message"),
    [
        (
            lambda n: {"labels": np.zeros(n - 1, dtype=int)},
            [],
            "pred.npz: 'labels' must hold one integer label per",
        ),
        (lambda n: {"labels": np.zeros(n)}, [], "pred.npz: 'labels' must hold one integer label per event"),
        (
            lambda n: {"cluster": np.zeros(n, dtype=int)},
            [],
            "pred.npz: no per-event label field 'labels' and no",
        ),
        (
            lambda n: {"labels": np.zeros(n, dtype=int)},
            ["--prediction-field", "c"],
            "no per-event label field 'c'",
        ),
        (
            lambda n: {"masks": np.zeros((1, 90, 120), dtype=int)},
            [],
            "pred.npz: 'masks' needs its times in one",
        ),
        (
            lambda n: {"masks": np.zeros((1, 120, 90), dtype=int), "mask_times": [0.0]},
            [],
            "pred.npz: masks are (120, 90) (H, W) but the sensor is (90, 120)",
        ),
        (
            lambda n: {"masks": np.zeros((2, 90, 120), dtype=int), "mask_times": [0.02, 0.01]},
            [],
            "pred.npz: mask times must be finite and strictly increasing",
        ),
        (lambda n: {"labels": np.zeros(n, dtype=int)}, ["--config", "x.yaml"], "--config has no effect"),
    ],
)
def test_evaluate_labelled_bad_predictions(tmp_path, capsys, fields, args, message):
    path = _labelled_file(tmp_path, 0, 1)
    pred = tmp_path / "pred.npz"
    np.savez(pred, **fields(len(np.load(path)["label"])))
    assert main(["--quiet", "evaluate", "labelled", str(path), "--predictions", str(pred), *args]) == 2
    assert message in error_line(capsys)


def test_evaluate_labelled_prediction_count_and_folder(tmp_path, capsys):
    paths = [_labelled_file(tmp_path, 0, 1), _labelled_file(tmp_path, 1, 1)]
    folder = _truth_as_predictions(tmp_path / "net", paths[:1])
    command = ["--quiet", "evaluate", "labelled", *map(str, paths), "--predictions"]
    assert main([*command, str(folder / "probe_0.npy")]) == 2
    assert "1 predictions for 2 labelled files" in error_line(capsys)
    assert main([*command, str(folder)]) == 2
    assert f"{folder}: holds no prediction probe_1.npz/.npy" in error_line(capsys)


def test_evaluate_labelled_fails_before_any_progress(tmp_path, capsys):
    """A bad second file is reported alone: no progress bar is drawn before the files are checked."""
    paths = [_labelled_file(tmp_path, 0, 1), tmp_path / "missing.npz"]
    assert main(["evaluate", "labelled", *map(str, paths)]) == 2
    assert "missing.npz: no such file" in error_line(capsys)

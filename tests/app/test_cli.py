"""The ``evseg`` entry point: help, the console script, argument types, ``demo``."""

import json
import subprocess
import sys

import pytest

from evseg_torch.app.cli import main


@pytest.mark.parametrize(
    "command",
    [[], ["segment"], ["demo"], ["simulate"], ["evaluate"], ["evaluate", "eed"], ["evaluate", "labelled"]],
)
def test_help_is_clear(command, capsys):
    with pytest.raises(SystemExit) as stop:
        main([*command, "--help"])
    assert stop.value.code == 0
    assert "usage: evseg" in capsys.readouterr().out


def test_console_script_runs():
    command = [sys.executable, "-m", "evseg_torch.app.cli", "--help"]
    out = subprocess.run(command, capture_output=True, text=True)
    assert out.returncode == 0 and "segment" in out.stdout


def test_bad_sensor_size_argument(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["segment", "x.txt", "--out", "o", "--sensor-size", "big"])
    assert stop.value.code == 2
    assert "HxW" in capsys.readouterr().err


def test_demo_writes_figure_and_metrics(tmp_path):
    assert main(["--quiet", "demo", "--out", str(tmp_path)]) == 0
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["clusters"] == metrics["true_clusters"] == 3
    assert metrics["accuracy"] > 0.8 and metrics["mean_imo_iou"] > 0.7  # 0.90 and 0.85 measured
    assert (tmp_path / "demo.png").stat().st_size > 10_000

"""The README runs as written: its Python quickstart and learning example, its figures' commands, and every
`evseg` command it shows (each parses; the cheap ones run)."""

import glob
import importlib.metadata
import importlib.util
import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from evseg_torch.app.cli import main
from evseg_torch.app.cli.entry import build_parser

README = Path(__file__).resolve().parents[1] / "README.md"


def test_quickstart_runs(capsys):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.DOTALL)
    assert blocks, "the README has no Python quickstart"
    exec(compile(blocks[0], "README.md", "exec"), {})
    assert "accuracy" in capsys.readouterr().out


def test_learning_pipelines_example_runs(capsys, monkeypatch):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.DOTALL)
    example = next(block for block in blocks if "MultiModelContrastLoss" in block)
    root = README.parent
    if not (root.parent / "shared" / "data" / "synthetic_probe").is_dir():
        pytest.skip("the probe scenes are not beside the repository")
    monkeypatch.chdir(root)  # the example names the data relative to the repository
    exec(compile(example, "README.md", "exec"), {})
    loss, *shapes = capsys.readouterr().out.split(maxsplit=1)
    assert float(loss) < 0 and "torch.Size([3, 2, 4])" in shapes[0]


def test_every_figure_names_the_command_that_makes_it():
    spec = importlib.util.spec_from_file_location("make_figures", README.parent / "docs" / "make_figures.py")
    make_figures = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(make_figures)
    text = README.read_text()
    commands = make_figures.figure_commands(text)
    assert set(commands) == set(re.findall(r"\]\((docs/[^)]+\.png)\)", text)) and commands
    for path, command in commands.items():
        assert (README.parent / path).is_file()
        assert str(Path(path).parent) in command.split()  # the command writes into the figure's folder


# Every `evseg ...` line of the README's bash blocks: each parses with the real argument parser (so a flag
# the README shows exists), and the cheap ones run in a temporary folder.

SHARED = README.parent.parent / "shared"
# README placeholders this test can write (a small synthetic recording); other inputs that do not exist are
# only parsed (ROS bags, Prophesee files, EV-IMO sequences, a cluster's paths).
RECORDING_MS = 60


def readme_commands() -> list[list[str]]:
    """The ``evseg`` command lines of the README's ```bash blocks, as argument lists (comments dropped)."""
    blocks = re.findall(r"```bash\n(.*?)```", README.read_text(), flags=re.DOTALL)
    lines = "\n".join(blocks).replace("\\\n", " ").splitlines()
    return [shlex.split(line, comments=True) for line in lines if line.strip().startswith("evseg ")]


def figure_commands() -> list[list[str]]:
    """The commands under the README's figures (``Made by `evseg ...```), which ``make figures`` runs."""
    return [shlex.split(command) for command in re.findall(r"Made by `(evseg [^`]+)`", README.read_text())]


def test_readme_shows_commands():
    commands = readme_commands()
    shown = {tuple(word for word in argv[1:3] if not word.startswith("-")) for argv in commands}
    for command in [("demo",), ("simulate",), ("segment",)]:
        assert any(found[: len(command)] == command for found in shown), command
    for protocol in ["synthetic", "labelled", "eed", "evimo"]:
        assert ("evaluate", protocol) in {found[:2] for found in shown}, protocol


@pytest.mark.parametrize("argv", readme_commands() + figure_commands(), ids=" ".join)
def test_readme_command_parses(argv, capsys):
    try:
        build_parser().parse_args(argv[1:])
    except SystemExit as error:
        raise AssertionError(f"`{' '.join(argv)}` does not parse: {capsys.readouterr().err}") from error


def write_recording(folder: Path) -> None:
    """``recording.txt`` (rpg layout: ``t x y p``, t in seconds) from one synthetic scene."""
    from evseg_torch.synthetic import make_scene

    events = make_scene(sensor_size=(180, 240), duration=RECORDING_MS / 1000, n_objects=1, rng=3).events
    table = np.column_stack([events["t"] / 1e6, events["x"], events["y"], events["p"] > 0])
    np.savetxt(folder / "recording.txt", table, fmt=["%.6f", "%d", "%d", "%d"])


def runnable(argv: list[str], folder: Path) -> str | None:
    """Why a README command is only parsed here, or None when it runs (cheap, and its inputs exist)."""
    words = argv[1:]
    if any(word.startswith(("--scheduler", "--workers", "--predictions", "--figures")) for word in words):
        return "needs a cluster, worker processes, predictions or writes the README's figures"
    if words[:2] == ["evaluate", "synthetic"]:
        seeds = words[words.index("--seeds") + 1] if "--seeds" in words else "0-19"
        return None if "-" not in seeds and "," not in seeds and "--pipeline-seeds" not in words else "long"
    if words[0] in ("demo", "simulate"):
        return None
    if words[0] == "segment":
        inputs = []
        for word in words[1:]:
            if word.startswith("-"):
                break
            inputs.append(word)
        if any("shared" in word for word in inputs):
            return "reads ../shared/data (covered by tests/test_cli.py)"
        missing = [word for word in inputs if not glob.glob(str(folder / word))]
        return f"no {', '.join(missing)} here" if missing else None
    return "long or needs data absent here (covered by tests of evaluation/)"


def test_cheap_readme_commands_run(tmp_path, monkeypatch, capsys):
    """The README's cheap commands run, in its order, in one folder (``simulate`` writes what ``segment``
    reads); ``recording.txt`` is a generated 60 ms recording."""
    monkeypatch.chdir(tmp_path)
    write_recording(tmp_path)
    ran = []
    for argv in readme_commands():
        if runnable(argv, tmp_path) is not None:
            continue
        words = [expanded for word in argv[1:] for expanded in (sorted(glob.glob(word)) or [word])]
        assert main(["--quiet", *words]) == 0, f"`{' '.join(argv)}` failed: {capsys.readouterr().err}"
        ran.append(words[0])
    assert {"demo", "simulate", "segment", "evaluate"} <= set(ran), ran

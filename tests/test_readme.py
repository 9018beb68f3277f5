"""The README's Python quickstart runs exactly as written."""

import importlib.util
import re
from pathlib import Path

import pytest

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

"""The package works installed from a wheel, not only from the source tree.

A wheel is built from a copy of the sources (so the checkout gains no ``build/``), installed without
network into a fresh virtual environment of the base interpreter, and run from a folder outside the
repository: the bundled configs must come from the installed package. The environment reaches the
dependencies (torch, ...) of the interpreter running the tests through a ``.pth`` file, which appends
that interpreter's site-packages after the environment's own, so the installed ``evseg_torch`` wins.
"""

import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(command: list, cwd: Path) -> subprocess.CompletedProcess:
    # An inherited PYTHONPATH would put the source tree back in front of the installed package.
    env = {"PATH": "/usr/bin:/bin", "HOME": str(cwd), "OMP_WAIT_POLICY": "PASSIVE"}
    return subprocess.run(
        [str(part) for part in command], cwd=cwd, env=env, capture_output=True, text=True, timeout=150
    )


@pytest.mark.slow
@pytest.mark.realdata
def test_installed_wheel_evaluates_eed_with_its_bundled_config(tmp_path, real_data):
    sequence = real_data / "eed_what_is_background"
    source = tmp_path / "source"
    shutil.copytree(
        ROOT / "evseg_torch", source / "evseg_torch", ignore=shutil.ignore_patterns("__pycache__")
    )
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, source / name)
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "--no-input"]
    built = _run(
        [*pip, "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-w", tmp_path, source], tmp_path
    )
    assert built.returncode == 0, built.stderr
    (wheel,) = tmp_path.glob("evseg_torch-*.whl")

    venv = tmp_path / "venv"
    made = _run(
        [getattr(sys, "_base_executable", sys.executable), "-m", "venv", "--without-pip", venv], tmp_path
    )
    assert made.returncode == 0, made.stderr
    python = venv / "bin" / "python"
    installed = _run([*pip, "--python", python, "install", "--no-deps", "--no-index", wheel], tmp_path)
    assert installed.returncode == 0, installed.stderr
    site = _run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], tmp_path)
    (Path(site.stdout.strip()) / "evseg_test_dependencies.pth").write_text(
        sysconfig.get_paths()["purelib"] + "\n"
    )

    where = _run([python, "-c", "import evseg_torch; print(evseg_torch.__file__)"], tmp_path)
    assert Path(where.stdout.strip()).is_relative_to(venv), where.stdout + where.stderr
    run = _run([venv / "bin" / "evseg", "evaluate", "eed", sequence], tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "EED detection rate" in run.stdout and "what_is_background      14" in run.stdout

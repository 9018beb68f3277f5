"""Run the commands behind ``docs/benchmarks.md`` (``make bench``) and keep what each printed.

Every line of the page's ```bash blocks that starts with ``python benchmarks/`` or ``evseg `` is run
from the repository root, in the page's order, one after another (``python`` is this interpreter,
``evseg`` the console script beside it), with ``OMP_WAIT_POLICY=PASSIVE``. Each command's output goes to
``docs/_build/benchmarks/NN-<script>.txt`` under a header naming the command, the date, the machine's
CPU, the thread settings and the version (``git describe``), so a table can be updated from it. Ratios
against an older version (the page's "÷ v0.2" columns) need that version run at the same time on the
other core: run the same command in a worktree of the tag (``git worktree add ../v0.2 v0.2``).

    python benchmarks/run_docs_commands.py [--list] [--only NAME ...]

Commands whose data (``../shared/data``) is absent fail like any other and are listed at the end; the
rest still run. The whole page takes well over an hour on two cores.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import re
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "benchmarks.md"
OUT = ROOT / "docs" / "_build" / "benchmarks"


def page_commands(text: str) -> list[str]:
    """The page's benchmark and ``evseg`` command lines, in order."""
    blocks = re.findall(r"```bash\n(.*?)```", text, flags=re.DOTALL)
    lines = [line.strip() for block in blocks for line in block.replace("\\\n", " ").splitlines()]
    return [line for line in lines if line.startswith(("python benchmarks/", "evseg "))]


def argv(command: str) -> list[str]:
    """The command as run here: ``python`` is this interpreter, ``evseg`` the script beside it."""
    words = shlex.split(command, comments=True)
    if words[0] == "python":
        return [sys.executable, *words[1:]]
    return [str(Path(sys.executable).with_name("evseg")), *words[1:]]


def cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return f"{line.split(':', 1)[1].strip()}, {os.cpu_count()} cores"
    except OSError:
        pass
    return f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores"


def version() -> str:
    described = subprocess.run(
        ["git", "describe", "--tags", "--always", "--dirty"], cwd=ROOT, capture_output=True, text=True
    )
    return described.stdout.strip() or "unknown"


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--list", action="store_true", help="print the commands, run none")
    parser.add_argument("--only", nargs="+", metavar="NAME", help="only the commands containing NAME")
    options = parser.parse_args(args)
    commands = page_commands(PAGE.read_text())
    if options.only:
        commands = [command for command in commands if any(name in command for name in options.only)]
    if options.list:
        print("\n".join(commands))
        return 0
    OUT.mkdir(parents=True, exist_ok=True)
    environment = {**os.environ, "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
    header = f"machine: {cpu()}\nOMP_WAIT_POLICY={environment['OMP_WAIT_POLICY']}\nversion: {version()}\n"
    failed = []
    for number, command in enumerate(commands, start=1):
        name = Path(shlex.split(command)[1]).stem if command.startswith("python") else "evseg"
        log = OUT / f"{number:02d}-{name}.txt"
        print(f"$ {command}  > {log.relative_to(ROOT)}", flush=True)
        started = datetime.datetime.now().astimezone()
        result = subprocess.run(argv(command), cwd=ROOT, env=environment, capture_output=True, text=True)
        log.write_text(
            f"$ {command}\ndate: {started:%Y-%m-%d %H:%M %Z}\n{header}exit status: {result.returncode}\n\n"
            f"{result.stdout}{result.stderr}"
        )
        if result.returncode != 0:
            failed.append(command)
    if failed:
        print("failed:\n  " + "\n  ".join(failed), file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

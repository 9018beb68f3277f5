"""Regenerate the README's figures from the commands printed beside them (``make figures``).

Every figure in README.md is an image line ``![...](docs/NAME.png)`` followed, within the next
eight lines (its caption), by the line ``Made by `evseg ...` `` that names the command writing it.
This script finds those pairs, runs each distinct command once from the repository root (``evseg``
is this checkout's ``python -m evseg_torch.app.cli``) and checks that every figure was written anew, so
the README's figures and commands cannot drift apart. ``--only NAME ...`` regenerates the figures
whose path contains NAME, e.g. ``--only demo`` (the EED figures take a minute).
"""

from __future__ import annotations

import argparse
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
IMAGE = re.compile(r"!\[[^\]]*\]\((docs/[^)]+\.png)\)")
COMMAND = re.compile(r"Made by `(evseg [^`]+)`")


def figure_commands(readme: str) -> dict[str, str]:
    """Each README figure's path (relative to the root) mapped to the command that writes it."""
    lines = readme.splitlines()
    commands = {}
    for number, line in enumerate(lines):
        for path in IMAGE.findall(line):
            found = [COMMAND.search(after) for after in lines[number + 1 : number + 9]]
            made_by = next((match.group(1) for match in found if match), None)
            if made_by is None:
                raise SystemExit(f"README.md line {number + 1}: {path} has no 'Made by `evseg ...`' line")
            commands[path] = made_by
    return commands


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="+", metavar="NAME", help="only the figures whose path contains NAME")
    args = parser.parse_args(argv)
    commands = figure_commands((ROOT / "README.md").read_text())
    if args.only:
        commands = {path: cmd for path, cmd in commands.items() if any(name in path for name in args.only)}
    for command in dict.fromkeys(commands.values()):
        started = time.time()
        print(f"$ {command}", flush=True)
        subprocess.run(
            [sys.executable, "-m", "evseg_torch.app.cli", *shlex.split(command)[1:]], cwd=ROOT, check=True
        )
        stale = [
            path
            for path, made_by in commands.items()
            if made_by == command
            and not ((ROOT / path).is_file() and (ROOT / path).stat().st_mtime >= started)
        ]
        if stale:
            raise SystemExit(f"`{command}` did not write {', '.join(stale)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

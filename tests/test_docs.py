"""The documentation builds without warnings, and the commands it shows exist.

The Sphinx build (``make docs``) turns every warning into an error here: a docstring that docutils
cannot parse, an ambiguous cross-reference or a Markdown page outside every table of contents fails
this test, with the warnings listed by file.
"""

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from evseg_torch.app.cli.entry import build_parser

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted(DOCS.rglob("*.md"))]
PAGES = [page for page in PAGES if "_build" not in page.parts]


@pytest.mark.slow
def test_reference_builds_without_warnings(tmp_path):
    pytest.importorskip("sphinx")
    pytest.importorskip("myst_parser")
    options = ["-W", "--keep-going", "-b", "html", "-q", "-d", str(tmp_path / "trees")]
    command = [sys.executable, "-m", "sphinx", *options, str(DOCS), str(tmp_path / "html")]
    build = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    warnings = [line for line in build.stderr.splitlines() if re.search(r"(WARNING|ERROR|CRITICAL):", line)]
    assert build.returncode == 0, f"{len(warnings)} warnings:\n" + "\n".join(warnings or [build.stderr])
    assert (tmp_path / "html" / "index.html").is_file()
    assert (tmp_path / "html" / "api" / "evseg_torch.pipeline.html").is_file()


def test_pages_speak_of_versions():
    """Baselines are versions (v0.2), and the pages describe the software, not how its work went."""
    pattern = re.compile(r"this stop|the stop before|stop [0-9]|the [a-z]+ issue\b|issue [0-9]", re.I)
    found = [
        f"{page.relative_to(ROOT)}:{number}: {line.strip()}"
        for page in PAGES
        for number, line in enumerate(page.read_text().splitlines(), start=1)
        if pattern.search(line)
    ]
    assert not found, "\n".join(found)


def shown_commands(page: Path) -> list[list[str]]:
    """The ``python benchmarks/...`` and ``evseg ...`` lines of a page's ```bash blocks."""
    blocks = re.findall(r"```bash\n(.*?)```", page.read_text(), flags=re.DOTALL)
    lines = [line.strip() for block in blocks for line in block.replace("\\\n", " ").splitlines()]
    return [shlex.split(line, comments=True) for line in lines if line.startswith(("python bench", "evseg "))]


BENCHMARK_COMMANDS = [
    argv for page in (ROOT / "README.md", DOCS / "benchmarks.md") for argv in shown_commands(page)
]


def test_benchmarks_page_shows_its_commands():
    assert any(argv[0] == "python" for argv in BENCHMARK_COMMANDS)
    assert any(argv[0] == "evseg" for argv in shown_commands(DOCS / "benchmarks.md"))


@pytest.mark.parametrize("argv", BENCHMARK_COMMANDS, ids=" ".join)
def test_shown_command_exists(argv, capsys):
    """A benchmark script the pages name exists and takes the flags they give it (its own, or those of
    the benchmark modules it imports); an ``evseg`` command parses."""
    if argv[0] == "evseg":
        try:
            build_parser().parse_args(argv[1:])
        except SystemExit as error:
            raise AssertionError(f"`{' '.join(argv)}` does not parse: {capsys.readouterr().err}") from error
        return
    script = ROOT / argv[1]
    assert script.is_file(), f"{argv[1]} does not exist"
    source = script.read_text()
    for imported in re.findall(r"^from (bench_\w+) import", source, flags=re.M):
        source += (script.parent / f"{imported}.py").read_text()
    for flag in (word.split("=")[0] for word in argv[2:] if word.startswith("--")):
        assert f'"{flag}"' in source, f"{argv[1]} takes no {flag}"

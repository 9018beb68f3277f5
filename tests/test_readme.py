"""The README's Python quickstart runs exactly as written."""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_quickstart_runs(capsys):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.DOTALL)
    assert blocks, "the README has no Python quickstart"
    exec(compile(blocks[0], "README.md", "exec"), {})
    assert "accuracy" in capsys.readouterr().out

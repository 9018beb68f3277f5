"""Collection of the doctests (``--doctest-modules evseg_torch``): a module whose optional dependency is not
installed is left out rather than failing to import (the ``fast`` extra's Numba)."""

from pathlib import Path

collect_ignore = []
try:
    import numba  # noqa: F401
except ImportError:
    root = Path(__file__).parent
    collect_ignore += [str(path.relative_to(root)) for path in (root / "evseg_torch").glob("*/*_kernel.py")]

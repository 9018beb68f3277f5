"""Collection of the doctests (``--doctest-modules evseg_torch``): without Numba (the ``fast`` extra) the
compiled kernels, which import it, are left out rather than failing to import."""

from pathlib import Path

collect_ignore = []
try:
    import numba  # noqa: F401
except ImportError:
    root = Path(__file__).parent
    collect_ignore += [
        str(path.relative_to(root)) for path in (root / "evseg_torch" / "kernels").glob("[!_]*.py")
    ]

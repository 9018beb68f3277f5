"""Collection of the doctests (``--doctest-modules evseg_torch``): a module whose optional dependency is not
installed is left out rather than failing to import (the ``fast`` extra's Numba)."""

collect_ignore = []
try:
    import numba  # noqa: F401
except ImportError:
    collect_ignore += [f"evseg_torch/level_two/{name}_kernel.py" for name in ("fit", "graph", "solver")]

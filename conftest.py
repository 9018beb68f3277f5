"""Collection of the doctests (``--doctest-modules evseg_torch``): a module whose optional dependency is not
installed is left out rather than failing to import (the ``fast`` extra's Numba)."""

collect_ignore = []
try:
    import numba  # noqa: F401
except ImportError:
    collect_ignore += ["evseg_torch/level_two/fit_kernel.py", "evseg_torch/level_two/graph_kernel.py"]

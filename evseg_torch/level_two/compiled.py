"""Level two's compiled steps: found where Numba (the optional ``fast`` extra) is installed.

Some steps have a compiled form in a ``*_kernel`` module that gives the NumPy and tensor code's results
bit for bit (the site graph's weights, L-BFGS's bookkeeping, the data term's images); the fits' compiled
evaluation, which differs by rounding, is chosen by ``level_two.fit_backend`` instead
(:func:`~evseg_torch.level_two.cmax.resolve_fit_backend`).
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Callable


@functools.cache
def compiled_step(name: str) -> Callable | None:
    """The compiled form of a step where Numba is installed, else ``None``.

    Args:
        name: ``"module.function"`` in :mod:`evseg_torch.level_two`, e.g. ``"graph_kernel.pair_counts"``.
            The module is imported on first use, so that importing the package does not load Numba.
    """
    module, function = name.rsplit(".", 1)
    try:
        return getattr(importlib.import_module(f"evseg_torch.level_two.{module}"), function)
    except ImportError:
        return None

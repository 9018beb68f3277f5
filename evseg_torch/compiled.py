"""Compiled steps, found where Numba (the optional ``fast`` extra) is installed.

Some steps have a compiled form in a ``*_kernel`` module that gives the NumPy and tensor code's results
bit for bit (level two's site-graph weights, L-BFGS's bookkeeping and data term; α-expansion's move
graphs); level two's compiled fit evaluation, which differs by rounding, is chosen by
``level_two.fit_backend`` instead (:func:`~evseg_torch.level_two.cmax.resolve_fit_backend`).
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Callable


@functools.cache
def compiled_step(name: str) -> Callable | None:
    """The compiled form of a step where Numba is installed, else ``None``.

    Args:
        name: ``"package.module.function"`` in :mod:`evseg_torch`, e.g.
            ``"level_two.graph_kernel.pair_counts"``. The module is imported on first use, so that
            importing the package does not load Numba.
    """
    module, function = name.rsplit(".", 1)
    try:
        return getattr(importlib.import_module(f"evseg_torch.{module}"), function)
    except ImportError:
        return None

"""Where the compiled kernels run: the one setting that chooses them, read here only.

Several steps of level two and of the graph cuts have a compiled form in :mod:`evseg_torch.kernels`
(Numba, the optional ``fast`` extra) beside their tensor or NumPy code: the fits' evaluation, the data
term's images, L-BFGS's bookkeeping, the site graph's weights and α-expansion's move graphs. One
process-wide setting chooses:

* ``auto`` (default): the kernels where Numba is installed, else the tensor and NumPy code;
* ``numba``: the kernels (a :class:`~evseg_torch.errors.ConfigError` without Numba);
* ``torch``: the tensor and NumPy code everywhere.

It starts from the environment variable ``EVSEG_BACKEND`` and changes with :func:`set_backend` (the
command line's ``--backend``). A kernel serves only where it applies (float32 arrays on the CPU, no
gradient to keep); a GPU or autograd takes the tensor code whatever the setting. Every kernel gives its
code's results bit for bit except the fits' evaluation, which differs by rounding (losses within about
2e-7), so ``torch`` and ``numba`` segment alike up to the decisions that rounding tips.
"""

from __future__ import annotations

import functools
import importlib
import importlib.util
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from evseg_torch.errors import ConfigError

__all__ = ["BACKENDS", "get_backend", "kernel", "set_backend", "using_backend"]

BACKENDS = ("auto", "numba", "torch")
"""The settings of :func:`set_backend`."""

_chosen: str | None = None  # None until read from the environment


def get_backend() -> str:
    """The current setting, one of :data:`BACKENDS` (first read from ``EVSEG_BACKEND``, default ``auto``).

    Raises:
        ConfigError: ``EVSEG_BACKEND`` holds something else.
    """
    global _chosen
    if _chosen is None:
        _chosen = _checked(os.environ.get("EVSEG_BACKEND", "auto"), "EVSEG_BACKEND")
    return _chosen


def set_backend(name: str) -> None:
    """Choose where the kernels run for the rest of the process (module docstring).

    Raises:
        ConfigError: ``name`` is not one of :data:`BACKENDS`, or is ``numba`` without Numba installed.
    """
    global _chosen
    _chosen = _checked(name, "backend")


@contextmanager
def using_backend(name: str) -> Iterator[None]:
    """:func:`set_backend` for the ``with`` block, then the setting before it."""
    before = get_backend()
    set_backend(name)
    try:
        yield
    finally:
        set_backend(before)


def kernel(name: str) -> Callable | None:
    """The compiled form of a step under the current setting, or ``None`` for its tensor or NumPy code.

    Args:
        name: ``"module.function"`` in :mod:`evseg_torch.kernels`, e.g. ``"fit.loss_and_grad"``; the
            module is imported on first use, so importing evseg_torch does not load Numba.
    """
    if get_backend() == "torch":
        return None
    return _compiled(name)


@functools.cache
def _compiled(name: str) -> Callable | None:
    if not _numba_installed():
        return None
    module, function = name.rsplit(".", 1)
    return getattr(importlib.import_module(f"evseg_torch.kernels.{module}"), function)


def _numba_installed() -> bool:
    return importlib.util.find_spec("numba") is not None


def _checked(name: str, what: str) -> str:
    if name not in BACKENDS:
        raise ConfigError(f"{what} must be one of {', '.join(BACKENDS)}, got {name!r}")
    if name == "numba" and not _numba_installed():
        raise ConfigError(f"{what} 'numba' needs the numba package: pip install 'evseg-torch[fast]'")
    return name

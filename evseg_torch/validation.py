"""Argument checks that many modules share, each with one wording."""

from __future__ import annotations

from numbers import Integral

from evseg_torch.errors import ConfigError, EvsegError

__all__ = ["check_integer"]


def check_integer(value, name: str, *, at_least: int = 0, error: type[EvsegError] = ConfigError) -> int:
    """``value`` as an ``int``, where it is an integer (Python's or NumPy's, never a bool) of at least
    ``at_least``.

    Raises:
        EvsegError: of type ``error``, naming ``name``, otherwise.

    Examples:
        >>> check_integer(3, "max_iter", at_least=1)
        3
        >>> check_integer(True, "max_iter")
        Traceback (most recent call last):
        ...
        evseg_torch.errors.ConfigError: max_iter must be an integer of at least 0, got True
    """
    if isinstance(value, bool) or not isinstance(value, Integral) or value < at_least:
        raise error(f"{name} must be an integer of at least {at_least}, got {value!r}")
    return int(value)

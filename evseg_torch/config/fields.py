"""How a config field is declared and validated: the machinery behind :mod:`evseg_torch.config`'s sections.

A section (:mod:`evseg_torch.config.sections`) is a frozen dataclass derived from :class:`Section`, each
field declared by :func:`setting` with its default and the bounds or choices its value must meet.
:class:`Section` checks every field when the section is built (``__post_init__``): its type (a bool is
not an integer; a float must be finite; an integer given for a float field becomes a float, a list for
a tuple field a tuple), its range and its choices, raising :class:`~evseg_torch.errors.ConfigError`
naming the key. Choices that an implementation registers (:class:`Names`) are looked up only then.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
import operator
import types
import typing
from dataclasses import field
from numbers import Integral, Real
from typing import ClassVar, NamedTuple

from evseg_torch.errors import ConfigError

__all__ = ["Names", "Section", "setting"]


class Names(NamedTuple):
    """The names an implementation registers (a module's tuple or dict), looked up when a value is
    validated: the modules import this one, so it cannot import them first."""

    module: str
    attribute: str

    def names(self) -> tuple[str, ...]:
        return tuple(getattr(importlib.import_module(self.module), self.attribute))


def setting(
    default,
    *,
    above: float | None = None,
    at_least: float | None = None,
    below: float | None = None,
    at_most: float | None = None,
    choices: tuple[str, ...] | Names | None = None,
):
    """A config field: its default and the bounds or choices its value must meet (``None``, where the
    field allows it, meets all of them)."""
    limits = {"above": above, "at_least": at_least, "below": below, "at_most": at_most, "choices": choices}
    return field(default=default, metadata={k: v for k, v in limits.items() if v is not None})


class Section:
    """Validation shared by every config section: each field's type, finiteness, range and choices."""

    where: ClassVar[str] = ""

    def __post_init__(self) -> None:
        hints = typing.get_type_hints(type(self))
        for spec in dataclasses.fields(self):
            key = f"{self.where}{spec.name}"
            value, hint = getattr(self, spec.name), hints[spec.name]
            if dataclasses.is_dataclass(hint):
                if not isinstance(value, hint):
                    raise ConfigError(
                        f"config key {key!r} must be a {hint.__name__}, got {type(value).__name__}"
                    )
                continue
            value = _coerce(value, hint, key)
            if value is not None:
                _check_limits(value, spec.metadata, key)
            object.__setattr__(self, spec.name, value)


def _coerce(value, hint, key: str):
    """``value`` as the type ``hint`` names (an int for a float field becomes a float; a list of a
    tuple field a tuple), or a ConfigError naming ``key``."""
    options = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else (hint,)
    if value is None:
        if type(None) in options:
            return None
        raise ConfigError(f"config key {key!r} must not be null")
    errors = []
    for option in options:
        if option is type(None):
            continue
        try:
            return _coerce_one(value, option)
        except (TypeError, ValueError) as err:
            errors.append(str(err))
    raise ConfigError(f"config key {key!r} has invalid value {value!r}: {'; '.join(errors)}")


def _coerce_one(value, hint):
    if typing.get_origin(hint) is tuple:
        kinds = typing.get_args(hint)
        any_length = kinds[-1] is Ellipsis  # tuple[X, ...]
        if not isinstance(value, list | tuple) or not (any_length or len(value) == len(kinds)):
            raise TypeError("expected a list" if any_length else f"expected a list of {len(kinds)} values")
        kinds = (kinds[0],) * len(value) if any_length else kinds
        return tuple(_coerce_one(v, k) for v, k in zip(value, kinds, strict=True))
    if hint is bool:
        if not isinstance(value, bool):
            raise TypeError("expected true or false")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, Integral):
            raise TypeError("expected an integer")
        return int(value)
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, Real):
            raise TypeError("expected a number")
        if not math.isfinite(value):
            raise ValueError("expected a finite number")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise TypeError("expected a string")
        return value
    raise TypeError(f"unsupported type {hint}")


_BOUNDS = {
    "above": (">", operator.gt),
    "at_least": (">=", operator.ge),
    "below": ("<", operator.lt),
    "at_most": ("<=", operator.le),
}


def _check_limits(value, limits, key: str) -> None:
    """Check a coerced value (each element of a tuple) against a field's bounds and choices."""
    if "choices" in limits:
        choices = limits["choices"]
        choices = choices.names() if isinstance(choices, Names) else choices
        if value not in choices:
            listed = ", ".join(map(repr, choices))
            raise ConfigError(f"config key {key!r} has invalid value {value!r}: expected one of {listed}")
    bounds = [(_BOUNDS[name], bound) for name, bound in limits.items() if name in _BOUNDS]
    for element in value if isinstance(value, tuple) else (value,):
        if not all(holds(element, bound) for (_, holds), bound in bounds):
            wanted = " and ".join(f"{symbol} {bound:g}" for (symbol, _), bound in bounds)
            noun = "integer" if isinstance(element, int) else "number"
            positive = {("above", 0), ("at_least", 1)} & set(limits.items())
            kind = f"a positive {noun}" if positive else {"integer": "an integer", "number": "a number"}[noun]
            raise ConfigError(f"config key {key!r} has invalid value {value!r}: expected {kind} {wanted}")

"""The config is the single source of every default: a public function's or constructor's keyword default
that stands for a config field equals that field's default.

Each row of ``DEFAULTS`` names a callable, the config section whose settings it takes, and how its
parameters map to that section's fields where the names differ: a field name, a function of the
section's defaults for a parameter that holds a field in another form (``win_size`` is
``(lk_win_size, lk_win_size)``), or ``None`` for a parameter that shares a field's name but is something
else (``progressive_x``'s ``initial_models`` are models, the config's ``initial_models`` a mode).
Parameters named like one of the section's fields need no entry: they are checked by name.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
from collections.abc import Callable
from typing import Any

import pytest

from evseg_torch.config import FeatureConfig, LevelOneConfig, LevelTwoConfig, SegmenterConfig, WindowConfig
from evseg_torch.level_one.features import detect_corners, extract_correspondences, to_uint8, track_features
from evseg_torch.level_one.gc_ransac import Correspondences, gc_ransac
from evseg_torch.level_one.progressive_x import progressive_x
from evseg_torch.motion import Rotation3D

Field = str | Callable[[dict[str, Any]], Any] | None


@dataclasses.dataclass(frozen=True)
class Defaults:
    """A callable, the config section it takes its settings from, and its parameters named otherwise."""

    function: Callable
    section: type
    fields: dict[str, Field] = dataclasses.field(default_factory=dict)


def _square(field: str) -> Callable[[dict[str, Any]], tuple]:
    return lambda defaults: (defaults[field], defaults[field])


LK_WINDOW = {"win_size": _square("lk_win_size"), "max_level": "lk_max_level"}

DEFAULTS = [
    Defaults(detect_corners, FeatureConfig, {"sigma": "corner_sigma"}),
    Defaults(track_features, FeatureConfig, LK_WINDOW),
    Defaults(extract_correspondences, FeatureConfig, {"sigma": "corner_sigma", **LK_WINDOW}),
    # The blur of the images Lucas-Kanade tracks, not the corners' (``corner_sigma``): no setting.
    Defaults(to_uint8, FeatureConfig, {"sigma": None}),
    Defaults(gc_ransac, LevelOneConfig),
    Defaults(Correspondences.build, LevelOneConfig),
    Defaults(progressive_x, LevelOneConfig, {"initial_models": None}),
    Defaults(Rotation3D, SegmenterConfig),
]

# Modules whose public callables must all be rows of DEFAULTS when a keyword default of theirs is named
# like a config field.
MODULES = [
    "evseg_torch.level_one.corners",
    "evseg_torch.level_one.features",
    "evseg_torch.level_one.gc_ransac",
    "evseg_torch.level_one.images",
    "evseg_torch.level_one.inliers",
    "evseg_torch.level_one.lucas_kanade",
    "evseg_torch.level_one.neighborhood",
    "evseg_torch.level_one.progressive_x",
    "evseg_torch.level_one.sampling",
    "evseg_torch.motion",
    "evseg_torch.tracking",
]


def _field_defaults(section: type) -> dict[str, Any]:
    return {f.name: f.default for f in dataclasses.fields(section) if f.default is not dataclasses.MISSING}


def _keyword_defaults(function: Callable) -> dict[str, Any]:
    parameters = inspect.signature(function).parameters.values()
    return {p.name: p.default for p in parameters if p.default is not inspect.Parameter.empty}


def _expected(defaults: dict[str, Any], field: Field):
    return field(defaults) if callable(field) else defaults[field]


@pytest.mark.parametrize("row", DEFAULTS, ids=lambda row: row.function.__qualname__)
def test_mapped_defaults_are_the_config_fields(row):
    """Every parameter the row maps to a field exists, and its default is that field's."""
    defaults = _field_defaults(row.section)
    keywords = _keyword_defaults(row.function)
    parameters = inspect.signature(row.function).parameters
    for name, field in row.fields.items():
        assert name in parameters, f"{row.function.__qualname__} has no parameter {name!r}"
        if field is None:
            continue
        assert (isinstance(field, str) and field in defaults) or callable(field), field
        expected = _expected(defaults, field)
        assert name in keywords, (
            f"{row.function.__qualname__}({name}) has no default; the config's is {expected!r}"
        )
        assert keywords[name] == expected and type(keywords[name]) is type(expected), (
            f"{row.function.__qualname__}({name}={keywords[name]!r}) but the config's default is {expected!r}"
        )


@pytest.mark.parametrize("row", DEFAULTS, ids=lambda row: row.function.__qualname__)
def test_defaults_named_like_fields_are_the_config_fields(row):
    """Every keyword default named like one of the section's fields, and not mapped, is that field's."""
    defaults = _field_defaults(row.section)
    for name, value in _keyword_defaults(row.function).items():
        if name in row.fields or name not in defaults:
            continue
        expected = defaults[name]
        assert value == expected and type(value) is type(expected), (
            f"{row.function.__qualname__}({name}={value!r}) but {row.section.__name__}.{name} is {expected!r}"
        )


def _public_callables(module_name: str):
    module = importlib.import_module(module_name)
    for name in getattr(module, "__all__", ()):
        value = getattr(module, name)
        if inspect.isfunction(value):
            yield value
        elif inspect.isclass(value):
            yield value
            for attribute, member in vars(value).items():
                function = getattr(member, "__func__", member)
                if not attribute.startswith("_") and inspect.isfunction(function):
                    yield getattr(value, attribute)


def test_every_default_named_like_a_field_has_a_row():
    """A public callable with a keyword default named like any config field is a row of DEFAULTS."""
    sections = (SegmenterConfig, WindowConfig, FeatureConfig, LevelOneConfig, LevelTwoConfig)
    fields = {f.name for section in sections for f in dataclasses.fields(section)}
    listed = {row.function for row in DEFAULTS}
    missing = sorted(
        {
            f"{function.__module__}.{function.__qualname__}({', '.join(sorted(shared))})"
            for module in MODULES
            for function in _public_callables(module)
            if (shared := set(_keyword_defaults(function)) & fields) and function not in listed
        }
    )
    assert not missing, f"add these to DEFAULTS: {missing}"

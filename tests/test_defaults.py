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
from evseg_torch.level_two.descent.segmenter import GraphCutContrastSegmenter
from evseg_torch.level_two.energy.data_term import DataCost, data_cost
from evseg_torch.level_two.energy.graph import event_graph, site_graph
from evseg_torch.level_two.image.splat import ImageOfWarpedEvents, splat_events, warped_iwe
from evseg_torch.level_two.objectives.contrast import ContrastLoss, contrast_loss, padded_contrast_loss
from evseg_torch.level_two.objectives.multi_model import MultiModelContrastLoss, multi_model_contrast_loss
from evseg_torch.level_two.solver.cmax import ContrastMaximization
from evseg_torch.level_two.solver.optimizers import adam, lbfgs
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
DATA_TERM = {
    "sigma": "data_sigma",
    "normalization": "data_normalization",
    "polarity": "data_polarity",
    "floor_quantile": "data_floor_quantile",
    "pool_floor_quantile": "data_pool_floor_quantile",
}

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
    Defaults(DataCost, LevelTwoConfig, DATA_TERM),
    Defaults(data_cost, LevelTwoConfig, DATA_TERM),
    Defaults(ContrastMaximization, LevelTwoConfig),
    # None: the module's (the config's) iterations, or the config's discovery rounds.
    Defaults(ContrastMaximization.forward, LevelTwoConfig, {"max_iter": None}),
    Defaults(GraphCutContrastSegmenter.forward, LevelTwoConfig, {"discovery_rounds": None}),
    # The optimisers' own steps, which the config's ``lr: null`` defers to.
    Defaults(lbfgs, LevelTwoConfig, {"lr": None}),
    Defaults(adam, LevelTwoConfig, {"lr": None}),
    Defaults(contrast_loss, LevelTwoConfig),
    Defaults(padded_contrast_loss, LevelTwoConfig),
    Defaults(ContrastLoss, LevelTwoConfig),
    Defaults(multi_model_contrast_loss, LevelTwoConfig),
    Defaults(MultiModelContrastLoss, LevelTwoConfig),
    # An image's blur (EMSGC's 1 px), the refits' ``sigma`` by default.
    Defaults(splat_events, LevelTwoConfig),
    Defaults(warped_iwe, LevelTwoConfig),
    Defaults(ImageOfWarpedEvents, LevelTwoConfig),
    Defaults(event_graph, LevelTwoConfig),
    Defaults(site_graph, LevelTwoConfig, {"time_slices": "site_time_slices"}),
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
    "evseg_torch.level_two.descent.segmenter",
    "evseg_torch.level_two.discovery",
    "evseg_torch.level_two.energy.data_term",
    "evseg_torch.level_two.energy.graph",
    "evseg_torch.level_two.energy.label_cost",
    "evseg_torch.level_two.image.blur",
    "evseg_torch.level_two.image.splat",
    "evseg_torch.level_two.image.warp",
    "evseg_torch.level_two.objectives.contrast",
    "evseg_torch.level_two.objectives.multi_model",
    "evseg_torch.level_two.objects",
    "evseg_torch.level_two.solver.cmax",
    "evseg_torch.level_two.solver.optimizers",
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

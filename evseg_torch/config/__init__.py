"""Hyper-parameters as nested frozen dataclasses, loaded strictly from YAML.

Every hyper-parameter of the pipeline is defined once: its default, its documentation and its
validation, in the sections of :mod:`evseg_torch.config.sections` (:class:`SegmenterConfig` and the
sections it holds), which are imported from here. Names follow EMSGC (``lambda_smooth``,
``lambda_label``, ``n_iter_segmentation``) and pyprogressivex (``threshold``, ``conf``,
``minimum_point_number``). Field names are unique across sections, so a flat keyword such as
``lambda_smooth=40`` names exactly one field (:func:`replace_config`).

Each section validates itself when it is built (``__post_init__``), from YAML, from keywords or by
:func:`dataclasses.replace`: a field's type (a bool is not an integer; a float must be finite), its range
(:func:`~evseg_torch.config.fields.setting`'s bounds) and its choices; an integer given for a float field
becomes a float. Unknown keys, in files or in keywords, and invalid values are
:class:`~evseg_torch.errors.ConfigError` naming the key (:mod:`evseg_torch.config.fields`). The modules
take their settings and their defaults from these sections
(:meth:`~evseg_torch.level_two.descent.segmenter.GraphCutContrastSegmenter.from_config`; the functions'
defaults are the fields' own), so a module's defaults are the config's.

Each field's documentation says what it does and, in a clause, why its default; the measurements
behind the defaults are kept in ``docs/notes/2026-12-07-settings.md``.

This module reads and writes configs: YAML files (:func:`load_config`, :func:`dump_config`), nested
dicts (:func:`config_from_dict`, :func:`config_to_dict`) and flat replacements (:func:`replace_config`).
The configs shipped with the package (``default.yaml``, a full listing of these defaults, the datasets'
``eed.yaml`` and ``evimo.yaml`` and the faster ``fast.yaml``, which list only what they change) are
package data, found by :func:`bundled_config`.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import typing
from pathlib import Path

import yaml

from evseg_torch.config.sections import (
    FeatureConfig,
    LevelOneConfig,
    LevelTwoConfig,
    SegmenterConfig,
    WindowConfig,
)
from evseg_torch.errors import ConfigError

__all__ = [
    "FeatureConfig",
    "LevelOneConfig",
    "LevelTwoConfig",
    "SegmenterConfig",
    "WindowConfig",
    "bundled_config",
    "config_from_dict",
    "config_to_dict",
    "dump_config",
    "load_config",
    "replace_config",
    "replace_settings",
    "shipped_configs",
]


def _configs_folder():
    """The package's folder of shipped configs (installed as files, a wheel or editable, never zipped)."""
    return importlib.resources.files("evseg_torch") / "configs"


def shipped_configs() -> tuple[str, ...]:
    """The names of the configs shipped with the package, sorted, without ``.yaml``: ``default``, ``eed``,
    ``evimo`` and ``fast``."""
    return tuple(
        sorted(
            item.name.removesuffix(".yaml")
            for item in _configs_folder().iterdir()
            if item.name.endswith(".yaml")
        )
    )


def bundled_config(name: str) -> Path:
    """The path of a config shipped with the package (:func:`shipped_configs`; ``.yaml`` optional).

    Raises:
        ConfigError: no such config is shipped.
    """
    stem = name.removesuffix(".yaml")
    shipped = shipped_configs()
    if stem not in shipped:
        raise ConfigError(f"no bundled config {name!r}; shipped: {', '.join(f'{s}.yaml' for s in shipped)}")
    return Path(str(_configs_folder() / f"{stem}.yaml"))


def replace_settings(section, **settings):
    """A copy of one config section with some fields replaced, validated; unknown names are errors."""
    names = [f.name for f in dataclasses.fields(section)]
    unknown = sorted(set(settings) - set(names))
    if unknown:
        raise ConfigError(
            f"unknown config key {section.where}{unknown[0]!r}; known keys here: {sorted(names)}"
        )
    return dataclasses.replace(section, **settings)


def config_from_dict(data: dict, cls: type = SegmenterConfig, where: str = ""):
    """Build a config dataclass from a (nested) mapping, rejecting unknown keys and invalid values."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where or 'config'} must be a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"unknown config key {where}{unknown[0]!r}; known keys here: {sorted(names)}")
    values = {
        name: config_from_dict(value, hints[name], f"{where}{name}.")
        if dataclasses.is_dataclass(hints[name])
        else value
        for name, value in data.items()
    }
    return cls(**values)


def config_to_dict(config) -> dict:
    """A plain nested dict of a config (tuples become lists), ready for YAML or JSON."""
    return _plain(dataclasses.asdict(config))


def load_config(path: str | Path) -> SegmenterConfig:
    """Load a YAML config file strictly; keys left out keep their defaults."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise ConfigError(f"cannot read config file {path}: {err.strerror or err}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise ConfigError(f"config file {path} is not valid YAML: {err}") from None
    try:
        return config_from_dict(data or {})
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None


def dump_config(config: SegmenterConfig, path: str | Path) -> None:
    """Write a config as YAML (it loads back equal with :func:`load_config`)."""
    Path(path).write_text(yaml.safe_dump(config_to_dict(config), sort_keys=False))


def replace_config(config: SegmenterConfig, **overrides) -> SegmenterConfig:
    """A copy of ``config`` with fields replaced by their flat names, e.g. ``lambda_smooth=40``.

    A whole section may be replaced too (``level_two=LevelTwoConfig(...)`` or a dict of its fields).
    """
    sections = [
        f.name for f in dataclasses.fields(config) if dataclasses.is_dataclass(getattr(config, f.name))
    ]
    top, nested = {}, {name: {} for name in sections}
    for key, value in overrides.items():
        if key in sections:
            top[key] = (
                value
                if dataclasses.is_dataclass(value)
                else config_from_dict(value, type(getattr(config, key)), f"{key}.")
            )
            continue
        owner = next(
            (s for s in sections if key in {f.name for f in dataclasses.fields(getattr(config, s))}), None
        )
        if owner is None and key not in {f.name for f in dataclasses.fields(config)}:
            raise ConfigError(f"unknown config key {key!r}")
        if owner is None:
            top[key] = value
        else:
            nested[owner][key] = value
    for section, values in nested.items():
        if values:
            top[section] = dataclasses.replace(top.get(section, getattr(config, section)), **values)
    return dataclasses.replace(config, **top)


def _plain(value):
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value

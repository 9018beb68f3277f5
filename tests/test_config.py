import dataclasses
import inspect

import numpy as np
import pytest
import torch
import yaml

from evseg_torch.config import (
    FeatureConfig,
    LevelOneConfig,
    LevelTwoConfig,
    SegmenterConfig,
    WindowConfig,
    bundled_config,
    config_from_dict,
    config_to_dict,
    dump_config,
    load_config,
    replace_config,
    shipped_configs,
)
from evseg_torch.errors import ConfigError
from evseg_torch.events import EventBatch
from evseg_torch.level_one.features import extract_correspondences
from evseg_torch.level_one.progressive_x import progressive_x
from evseg_torch.level_two.descent.segmenter import GraphCutContrastSegmenter
from evseg_torch.level_two.solver.cmax import ContrastMaximization
from evseg_torch.pipeline import CascadedSegmenter


def test_round_trip_default_to_yaml_and_back(tmp_path):
    config = replace_config(SegmenterConfig(), focal=(200.0, 210.0), stride_ms=10)
    dump_config(config, tmp_path / "c.yaml")
    assert load_config(tmp_path / "c.yaml") == config


def test_partial_file_keeps_defaults(tmp_path):
    (tmp_path / "c.yaml").write_text("level_two:\n  lambda_smooth: 40\nmotion_model: translation\n")
    config = load_config(tmp_path / "c.yaml")
    assert config.level_two.lambda_smooth == 40.0 and config.motion_model == "translation"
    assert config.level_two.lambda_label == SegmenterConfig().level_two.lambda_label


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("level_two:\n  lambda_smoth: 40\n", "unknown config key level_two.'lambda_smoth'"),
        ("colour: red\n", "unknown config key 'colour'"),
        ("level_two:\n  n_iter_segmentation: 2.5\n", "expected an integer"),
        ("level_two: 3\n", "must be a mapping"),
        ("window:\n  window_ms: fast\n", "expected a number"),
        ("[unclosed\n", "not valid YAML"),
    ],
)
def test_strict_errors_name_the_key(tmp_path, text, message):
    (tmp_path / "c.yaml").write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_config(tmp_path / "c.yaml")


def test_flat_overrides():
    config = replace_config(SegmenterConfig(), lambda_smooth=40, threshold=2.0, seed=3)
    assert config.level_two.lambda_smooth == 40.0 and config.level_one.threshold == 2.0 and config.seed == 3
    assert replace_config(config, level_two=LevelTwoConfig()).level_two == LevelTwoConfig()
    with pytest.raises(ConfigError, match="unknown config key 'lambda_smoth'"):
        replace_config(config, lambda_smoth=1)
    with pytest.raises(ConfigError, match="lambda_label"):
        replace_config(config, lambda_label="many")


def test_field_names_are_unique_across_sections():
    names = [
        key
        for section in config_to_dict(SegmenterConfig()).values()
        if isinstance(section, dict)
        for key in section
    ]
    assert len(names) == len(set(names))


def test_missing_file():
    with pytest.raises(ConfigError, match="cannot read config file"):
        load_config("no/such/file.yaml")
    assert config_from_dict({}) == SegmenterConfig()


@pytest.mark.parametrize("name", ["default", "eed", "evimo", "fast"])
def test_shipped_configs_load_strictly(name):
    config = load_config(bundled_config(name))
    assert isinstance(config, SegmenterConfig)


def test_shipped_configs_are_named_without_suffix():
    assert shipped_configs() == ("default", "eed", "evimo", "fast")
    assert bundled_config("fast.yaml") == bundled_config("fast")


def test_default_yaml_equals_dataclass_defaults():
    assert load_config(bundled_config("default.yaml")) == SegmenterConfig()
    with pytest.raises(ConfigError, match=r"no bundled config 'eds'; shipped: default\.yaml, eed\.yaml"):
        bundled_config("eds")


@pytest.mark.parametrize("name", ["eed", "evimo", "fast"])
def test_variant_configs_list_only_their_overrides(name):
    data = yaml.safe_load(bundled_config(name).read_text())
    defaults = config_to_dict(SegmenterConfig())
    for section, values in data.items():
        for key, value in values.items():
            assert value != defaults[section][key], f"{name}.yaml repeats the default {section}.{key}"


@pytest.mark.parametrize(
    ("section", "values", "message"),
    [
        (
            LevelTwoConfig,
            {"max_iter": True},
            "'level_two.max_iter' has invalid value True: expected an integer",
        ),
        (LevelTwoConfig, {"n_iter_segmentation": True}, "'level_two.n_iter_segmentation'"),
        (LevelTwoConfig, {"lambda_smooth": float("nan")}, "'level_two.lambda_smooth'.*finite"),
        (LevelTwoConfig, {"lambda_label": float("inf")}, "'level_two.lambda_label'.*finite"),
        (
            LevelTwoConfig,
            {"lr": 0.0},
            r"'level_two.lr' has invalid value 0.0: expected a positive number > 0",
        ),
        (LevelTwoConfig, {"optimizer": "sgd"}, "'level_two.optimizer'.*'lbfgs', 'adam'"),
        (LevelTwoConfig, {"objective": "entropy"}, "'level_two.objective'.*'variance'"),
        (LevelTwoConfig, {"data_normalization": "max"}, "'level_two.data_normalization'"),
        (LevelTwoConfig, {"label_tol": 1.0}, r"'level_two.label_tol'.*>= 0 and < 1"),
        (LevelTwoConfig, {"discovery_residual_cost": 300.0}, r"<= 255"),
        (LevelTwoConfig, {"temporal_edges": 1}, "'level_two.temporal_edges'.*true or false"),
        (LevelTwoConfig, {"collapse_weight": -0.1}, "'level_two.collapse_weight'"),
        (LevelOneConfig, {"conf": 1.0}, "'level_one.conf'"),
        (LevelOneConfig, {"max_iters": 10.0}, "'level_one.max_iters'.*expected an integer"),
        (LevelOneConfig, {"quality": "eq4"}, "'level_one.quality'.*'progressive_x', 'paper'"),
        (LevelOneConfig, {"initial_models": "merge"}, "'level_one.initial_models'"),
        (LevelOneConfig, {"extra_thresholds": [1.25, -1]}, r"'level_one.extra_thresholds'.*> 0"),
        (LevelOneConfig, {"extra_thresholds": 1.25}, "'level_one.extra_thresholds'.*expected a list"),
        (FeatureConfig, {"sub_window": 0.6}, "'features.sub_window'"),
        (FeatureConfig, {"lk_win_size": 2}, "'features.lk_win_size'"),
        (WindowConfig, {"window_ms": 0}, "'window.window_ms'"),
        (WindowConfig, {"events_per_window": True}, "'window.events_per_window'"),
        (SegmenterConfig, {"motion_model": "homography"}, "'motion_model'.*'affine4'"),
        (SegmenterConfig, {"focal": (200.0, -1.0)}, "'focal'"),
        (SegmenterConfig, {"seed": -1}, "'seed'"),
        (SegmenterConfig, {"level_two": {"lr": 1.0}}, "'level_two' must be a LevelTwoConfig"),
    ],
)
def test_every_section_validates_itself(section, values, message):
    with pytest.raises(ConfigError, match=message):
        section(**values)


def test_values_are_normalised():
    config = LevelTwoConfig(lambda_smooth=np.int64(40), max_iter=np.int64(4), lr=None)
    assert type(config.lambda_smooth) is float and type(config.max_iter) is int and config.lr is None
    assert SegmenterConfig(focal=[200, 210]).focal == (200.0, 210.0)
    assert LevelOneConfig(extra_thresholds=[1, 1.25]).extra_thresholds == (1.0, 1.25)


def test_lr_null_from_yaml_is_the_optimisers_default(tmp_path):
    (tmp_path / "c.yaml").write_text("level_two:\n  lr: null\n")
    assert load_config(tmp_path / "c.yaml").level_two.lr is None
    assert GraphCutContrastSegmenter("translation", (10, 10)).refit.lr == 1.0
    assert GraphCutContrastSegmenter("translation", (10, 10), optimizer="adam").refit.lr == 0.1


def test_every_module_keyword_is_a_config_field():
    two = {f.name for f in dataclasses.fields(LevelTwoConfig)}
    signature = inspect.signature(GraphCutContrastSegmenter)
    assert list(signature.parameters) == ["model", "sensor_size", "config", "settings"]
    # Level two's settings reach it as keywords (each one kept) or through from_config.
    for name in two:
        value = getattr(LevelTwoConfig(), name)
        segmenter = GraphCutContrastSegmenter("translation", (10, 10), **{name: value})
        assert segmenter.config == LevelTwoConfig()
    # The refits' keywords that level two sets are its settings (tol is the fits' own stopping rule).
    refit = set(inspect.signature(ContrastMaximization).parameters) - {"model", "sensor_size", "tol"}
    assert refit <= two
    # Every tuning keyword of Progressive-X is a level_one field, and the pipeline passes them all.
    data = {"src", "dst", "dt", "model", "initial_models", "rng"}
    one = LevelOneConfig().progressive_x_settings()
    assert set(inspect.signature(progressive_x).parameters) - data == set(one)
    # And every tuning keyword of the correspondences is a features field.
    data = {"events", "sensor_size", "sub_window_ms", "t_ref", "motion", "initial_models"}
    features = FeatureConfig().correspondence_settings()
    assert set(inspect.signature(extract_correspondences).parameters) - data == set(features)


def test_adam_from_yaml_runs_as_the_module_with_keywords(tmp_path):
    (tmp_path / "adam.yaml").write_text("motion_model: translation\nlevel_two:\n  optimizer: adam\n")
    sensor_size = (32, 32)
    from_yaml = CascadedSegmenter.from_config(tmp_path / "adam.yaml", sensor_size).level_two
    by_keyword = GraphCutContrastSegmenter("translation", sensor_size, optimizer="adam")
    assert from_yaml.config == by_keyword.config
    assert from_yaml.refit.lr == by_keyword.refit.lr == 0.1
    generator = torch.Generator().manual_seed(0)
    xy = torch.randint(0, 32, (400, 2), generator=generator).float()
    events = EventBatch(xy, torch.linspace(0, 0.01, 400), torch.ones(400))
    pool = torch.tensor([[0.0, 0.0], [300.0, -200.0]])
    first, second = from_yaml(events, pool), by_keyword(events, pool)
    assert torch.equal(first.labels, second.labels) and torch.equal(first.params, second.params)

from pathlib import Path

import pytest

from evseg_torch.config import (
    LevelTwoConfig,
    SegmenterConfig,
    config_from_dict,
    config_to_dict,
    dump_config,
    load_config,
    replace_config,
)
from evseg_torch.errors import ConfigError


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


CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.mark.parametrize("name", ["default.yaml", "eed.yaml", "evimo.yaml"])
def test_shipped_configs_load_strictly(name):
    config = load_config(CONFIGS / name)
    assert isinstance(config, SegmenterConfig)


def test_default_yaml_equals_dataclass_defaults():
    assert load_config(CONFIGS / "default.yaml") == SegmenterConfig()

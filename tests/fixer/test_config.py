"""Tests for gsfix_online/fixer/config.py: YAML/override round trip and validation."""

from __future__ import annotations

import pytest

from gsfix_online.core.config import ConfigError, build, to_dict, write_config
from gsfix_online.fixer.config import DEFAULT_PREDICTION_TYPE, FixerConfig


def test_defaults_follow_the_paper():
    cfg = FixerConfig()
    assert cfg.train.lr == 3e-5 and cfg.train.num_train_timesteps == 1000
    assert cfg.inference.steps == 4 and cfg.model.mode == "mesh+gs"
    # auto: SD2 keeps its checkpoint's (SD2-base: epsilon, the paper's); the default: x0
    assert cfg.model.prediction_type == "auto" and DEFAULT_PREDICTION_TYPE == "sample"


def test_overrides_and_yaml_round_trip(tmp_path):
    cfg = build(
        FixerConfig,
        overrides=[
            "model.mode=gs",
            "model.default.block_out_channels=[16, 32]",
            "masks.p_shared=0.5",
            "train.grad_accum=16",
            "inference.steps=1",
        ],
    )
    assert cfg.model.default.block_out_channels == (16, 32)
    path = write_config(cfg, tmp_path / "fixer.yaml")
    assert build(FixerConfig, files=[path]) == cfg
    assert to_dict(cfg)["masks"]["p_shared"] == 0.5


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("masks.p_shared=1.5", "out of range"),
        ("inference.steps=0", "out of range"),
        ("model.mode=depth", "one of"),
        ("model.source=sd2", "needs path"),
        ("model.default.block_out_channels=[12, 24]", "multiples of norm_num_groups"),
        ("masks.shape_area=[0.3, 0.1]", "shape_area"),
        ("model.prediction_type=epsilon", "residual needs prediction_type sample"),
        ("train.timestep_focus=2", "out of range"),
    ],
)
def test_invalid_values_are_one_line_errors(override, message):
    with pytest.raises(ConfigError, match=message):
        build(FixerConfig, overrides=[override])

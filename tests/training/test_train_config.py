"""Training config: presets follow the paper, every field is a command-line option, round trips."""

import argparse
from dataclasses import fields

import pytest

from crestereo_pp.cli.dataclass_args import add_dataclass_options, given_options, option_name
from crestereo_pp.training.config import PRESETS, SYNTHETIC, DataSource, TrainConfig, preset


def test_pretrain_preset_is_the_papers_first_stage():
    c = PRESETS["pretrain"]
    assert (c.lr, c.betas, c.crop_height, c.crop_width, c.gamma, c.max_steps) == (
        4e-4,
        (0.9, 0.999),
        384,
        512,
        0.8,
        150_000,
    )
    assert c.weight_decay == 0.0  # plain Adam


def test_finetune_preset_lowers_the_learning_rate():
    assert PRESETS["finetune"].lr == 1e-4 and PRESETS["finetune"].max_steps == 50_000


def test_preset_overrides_and_unknown_preset():
    assert preset("pretrain", batch_size=2).batch_size == 2
    with pytest.raises(ValueError, match="unknown training preset"):
        preset("nope")


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("synthetic", DataSource(SYNTHETIC, 1.0)),
        ("synthetic=0.25", DataSource(SYNTHETIC, 0.25)),
        ("/data/kitti=2", DataSource("/data/kitti", 2.0)),
    ],
)
def test_sources_parse_as_path_and_optional_weight(text, expected):
    assert DataSource.parse(text) == expected


def test_a_source_weight_must_be_positive_and_numeric():
    with pytest.raises(ValueError):
        DataSource.parse("synthetic=0")
    with pytest.raises(ValueError, match="PATH=WEIGHT"):
        DataSource.parse("a=b")


@pytest.mark.parametrize(
    "bad",
    [
        dict(crop_height=100),
        dict(sources=()),
        dict(batch_size=0),
        dict(real_scale_range=(1.2, 0.8)),
        dict(ema_decay=1.0),
        dict(ema_decay=-0.1),
        dict(texel_size=(0.8, 3.0)),  # texels under 1 px at the smallest scale: aliasing
        dict(texel_size=(3.0, 1.2)),
        dict(two_pass_fraction=1.5),
        dict(two_pass_fraction=-0.1),
        dict(two_pass_fraction=0.5, crop_height=96, crop_width=128),  # half of 96 is not a multiple of 32
        dict(thin_probability=1.5),
        dict(flat_probability=-0.1),
        dict(repetitive_probability=2.0),
        dict(wide_range_probability=0.5, wide_max_disparity=100.0),  # below the 192 px of 384x512 scenes
    ],
)
def test_invalid_configs_are_rejected(bad):
    with pytest.raises(ValueError):
        TrainConfig(**bad)


def test_scene_settings_of_the_config_reach_the_procedural_generator():
    config = TrainConfig(crop_height=64, crop_width=128, texel_size=(1.15, 2.5), photo_textures=2)
    scenes = config.scene_config
    assert (scenes.height, scenes.width, scenes.texel_size, scenes.photo_textures) == (64, 128, (1.15, 2.5), 2)
    assert config.scene_max_disparity == scenes.max_disparity == 48.0  # 192 * 128 / 512


def test_hard_case_knobs_are_off_by_default_and_reach_the_procedural_generator():
    default = TrainConfig().scene_config
    assert (default.thin_probability, default.flat_probability, default.repetitive_probability) == (0, 0, 0)
    assert default.wide_range_probability == 0 and default.wide_max_disparity == 256.0  # 256 * 512 / 512
    config = TrainConfig(
        thin_probability=0.3,
        flat_probability=0.2,
        repetitive_probability=0.1,
        wide_range_probability=0.5,
        wide_max_disparity=240.0,
        reflective_probability=0.4,
        row_offset_probability=0.5,
        row_offset=1.5,
    )
    scenes = config.scene_config
    assert (scenes.thin_probability, scenes.flat_probability, scenes.repetitive_probability) == (0.3, 0.2, 0.1)
    assert (scenes.wide_range_probability, scenes.wide_max_disparity) == (0.5, 240.0)
    assert scenes.reflective_probability == 0.4 and default.reflective_probability == 0
    assert (scenes.row_offset_probability, scenes.row_offset) == (0.5, 1.5) and default.row_offset_probability == 0
    assert TrainConfig.from_dict(config.to_dict()) == config


def test_config_round_trips_through_a_dict():
    config = preset(
        "finetune",
        sources=(DataSource(SYNTHETIC, 0.5), DataSource("/d", 0.5)),
        max_minutes=3.0,
        texel_size=(1.15, 2.5),
    )
    assert TrainConfig.from_dict(config.to_dict()) == config


def test_every_field_is_a_command_line_option_and_only_given_ones_override():
    parser = argparse.ArgumentParser()
    add_dataclass_options(parser, TrainConfig)
    args = parser.parse_args(
        [
            "--source",
            "synthetic=0.3",
            "--source",
            "/d=0.7",
            "--crop-height",
            "64",
            "--betas",
            "0.8",
            "0.9",
            "--max-minutes",
            "2.5",
            "--precision",
            "bf16",
            "--val-data",
            "/dev",
        ]
    )
    assert given_options(args, TrainConfig) == {
        "sources": (DataSource(SYNTHETIC, 0.3), DataSource("/d", 0.7)),
        "crop_height": 64,
        "betas": (0.8, 0.9),
        "max_minutes": 2.5,
        "precision": "bf16",
        "val_data": "/dev",
    }
    options = {a.dest for a in parser._actions}
    assert {f.name for f in fields(TrainConfig)} <= options
    assert option_name("sources") == "--source" and option_name("crop_width") == "--crop-width"


def test_choices_are_enforced_on_the_command_line():
    parser = argparse.ArgumentParser()
    add_dataclass_options(parser, TrainConfig)
    with pytest.raises(SystemExit):
        parser.parse_args(["--schedule", "exponential"])

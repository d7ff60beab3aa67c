"""One set of defaults (`hgca_core.config`): the Python API, every command and the drive take their defaults and
bounds from `CompletionConfig` / `DriveConfig`, and bad settings fail there with the field's name."""
from __future__ import annotations

import argparse

import numpy as np
import pytest

from hgca_core import cli
from hgca_core.errors import InputError

COMPLETING = ("complete", "drive", "demo", "eval", "bench")


def subparser(name: str) -> argparse.ArgumentParser:
    parser = cli.build_parser([name])
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


def option(p: argparse.ArgumentParser, flag: str) -> argparse.Action | None:
    return next((a for a in p._actions if flag in a.option_strings), None)


def test_every_completing_command_and_the_api_default_to_one_stage(monkeypatch):
    from hgca_core import config, pipeline

    want = config.CompletionConfig().stage
    for name in COMPLETING:
        assert option(subparser(name), "--stage").default == want, name
    seen = []

    def stop(stage, *a, **k):
        seen.append(stage)
        raise InputError("stop here")

    monkeypatch.setattr(pipeline, "load_models", stop)
    with pytest.raises(InputError, match="stop here"):
        pipeline.complete(np.zeros((20, 3)))
    assert seen == [want] == ["full"]
    import hgca_core

    with pytest.raises(InputError, match="stop here"):       # a config, and a keyword over it
        hgca_core.complete(np.zeros((20, 3)), config=hgca_core.CompletionConfig(stage="coarse", seed=3), stage="full")
    with pytest.raises(InputError, match="stop here"):
        hgca_core.complete(np.zeros((20, 3)), config=hgca_core.CompletionConfig(stage="coarse"))
    assert seen == ["full", "full", "coarse"]


def test_the_commands_shared_options_carry_the_configs_defaults():
    from hgca_core.config import CompletionConfig, DriveConfig

    c, d = CompletionConfig(), DriveConfig()
    for name, base in (("complete", c), ("drive", d.completion)):
        p = subparser(name)
        for flag, field in (("--samples", "samples"), ("--seed", "seed"), ("--device", "device"),
                            ("--precision", "precision"), ("--free-space", "free_space")):
            assert option(p, flag).default == getattr(base, field), (name, flag)
    p = subparser("drive")
    for flag, field in (("--size", "size"), ("--overlap", "overlap"), ("--scans-per-tile", "scans_per_tile"),
                        ("--workers", "workers"), ("--mesh-format", "mesh_format")):
        assert option(p, flag).default == getattr(d, field), flag


def test_commands_map_argv_to_the_config_the_library_gets():
    from hgca_core.commands.arguments import completion_config
    from hgca_core.commands.drive import drive_config
    from hgca_core.config import CompletionConfig, DriveConfig

    args = subparser("complete").parse_args(["s.ply", "-o", "m.ply", "--stage", "coarse", "--t1", "4",
                                             "--samples", "2"])
    assert completion_config(args) == CompletionConfig(stage="coarse", t1=4, samples=2)
    assert completion_config(subparser("complete").parse_args(["s.ply", "-o", "m.ply"])) == CompletionConfig()
    args = subparser("drive").parse_args(["s.ply", "-o", "d", "--size", "12.8", "--overlap", "3.2",
                                          "--tile-memory", "2"])
    assert drive_config(args) == DriveConfig(size=12.8, overlap=3.2, tile_memory=2 * 2**30)
    assert drive_config(args).completion.max_faces == 0          # a drive keeps every triangle of its tiles


def refused_by_both(change: dict, message: str, config, entry) -> None:
    """The settings class and the library entry point refuse the same bad setting with the same message."""
    for call in (config, entry):
        with pytest.raises(InputError, match=message):
            call(**change)


@pytest.mark.parametrize("change, message", [
    ({"stage": "fine"}, "stage must be one of preview, coarse, full"),
    ({"samples": 0}, "samples must be a whole number between 1"),
    ({"samples": True}, "samples must be a whole number"),
    ({"seed": -1}, "seed must be a whole number between 0 and 2\\*\\*63 - 1"),
    ({"seed": 2**63 - 1, "samples": 2}, "past 2\\*\\*63 - 1"),
    ({"t1": 1001}, "t1 must be a whole number >= 0 and at most 1000 \\(0: the weights' own\\)"),
    ({"t2": 2.5}, "t2 must be a whole number"),
    ({"max_faces": 10}, "max_faces must be 0 \\(keep every triangle\\) or at least 1000"),
    ({"device": "tpu"}, "unknown device 'tpu'"),
    ({"precision": "fp16"}, "precision must be one of auto, fp32, bf16"),
    ({"free_space": "maybe"}, "free_space must be one of auto, feature, mask, off"),
    ({"colour": "red"}, "unknown completion setting\\(s\\) colour"),
])
def test_a_bad_completion_setting_is_refused_by_name_before_any_work(change, message, monkeypatch):
    from hgca_core import pipeline
    from hgca_core.config import CompletionConfig

    monkeypatch.setattr(pipeline, "load_models", lambda *a, **k: pytest.fail("loaded models for a bad setting"))
    refused_by_both(change, message, CompletionConfig().with_, lambda **c: pipeline.complete(np.zeros((20, 3)), **c))


@pytest.mark.parametrize("change, message", [
    ({"size": 0.0}, "--size must be a finite tile side above 0 m"),
    ({"size": float("nan")}, "--size must be a finite tile side"),
    ({"overlap": 12.8, "size": 12.8}, "--overlap must be between 0 and the tile size"),
    ({"overlap": 12.7, "size": 12.8}, "the stride must be at least 0.2 m"),
    ({"scans_per_tile": 0}, "scans_per_tile must be a whole number at least 1"),
    ({"workers": 0}, "workers must be a whole number between 1"),
    ({"threads": 0}, "threads must be a whole number between 1"),
    ({"tile_memory": -1.0}, "tile_memory must be a finite number above 0"),
    ({"mesh_format": "stl"}, "mesh_format must be one of ply, glb, obj, npz"),
    ({"seams": "yes"}, "seams must be True or False"),
    ({"stage": "x"}, "stage must be one of preview, coarse, full"),
])
def test_a_bad_drive_setting_is_refused_by_name_before_reading_a_scan(change, message, tmp_path):
    import hgca_core
    from hgca_core.config import DriveConfig

    refused_by_both(change, message, DriveConfig().with_,
                    lambda **c: hgca_core.drive([str(tmp_path / "missing.ply")], tmp_path / "d", **c))
    assert not (tmp_path / "d").exists()


def test_drive_settings_route_to_the_drive_or_its_tiles():
    from hgca_core.config import CompletionConfig, DriveConfig

    d = DriveConfig().with_(stage="coarse", seed=4, size=12.8, overlap=3.2, max_faces=None)
    assert (d.size, d.overlap) == (12.8, 3.2)
    assert d.completion == CompletionConfig(stage="coarse", seed=4, max_faces=0)   # None: a tile's default


def test_one_number_parser_behind_positive_and_finite_floats():
    from hgca_core.commands import arguments

    assert arguments.positive_float.__code__ is arguments.finite_float.__code__
    assert arguments.positive_float("2.5") == 2.5 and arguments.finite_float("-3") == -3.0
    for parse, text, message in ((arguments.positive_float, "0", "above 0"), (arguments.finite_float, "inf", "finite"),
                                 (arguments.positive_float, "x", "not a number")):
        with pytest.raises(argparse.ArgumentTypeError, match=message):
            parse(text)

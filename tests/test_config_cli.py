"""The command line's surface: every option has help, `-o/--out` names the kind of thing it is, `complete` and
`drive` choose the mesh format the same way, and shared options have one definition."""
from __future__ import annotations

import argparse

import pytest

from hgca_core import cli
from test_config import option, subparser

FOLDER_OUT = {"drive", "demo", "bench", "synth", "train"}
FILE_OUT = {"complete": "MESH", "read": "FILE.npz", "poses": "FILE.json", "eval": "FILE.json",
            "eval-real": "FILE.json"}


@pytest.mark.parametrize("name", sorted(cli.COMMANDS))
def test_every_option_has_help(name):
    missing = [a.option_strings or a.dest for a in subparser(name)._actions
               if not isinstance(a, argparse._HelpAction) and (not a.help or a.help == argparse.SUPPRESS)]
    assert not missing, missing


@pytest.mark.parametrize("name", sorted(FOLDER_OUT | set(FILE_OUT)))
def test_out_is_one_flag_whose_metavar_says_what_it_is(name):
    out = option(subparser(name), "--out")
    assert out.option_strings == ["-o", "--out"], out.option_strings
    assert out.metavar == ("DIR" if name in FOLDER_OUT else FILE_OUT[name])
    assert ("folder" in out.help) == (name in FOLDER_OUT), out.help


def test_commands_that_write_are_the_ones_listed():
    writes = {name for name in cli.COMMANDS if option(subparser(name), "--out") is not None}
    assert writes == FOLDER_OUT | set(FILE_OUT)


@pytest.mark.parametrize("name", sorted(cli.COMMANDS))
def test_device_is_validated_while_parsing_everywhere(name):
    from hgca_core.commands.arguments import device_arg

    device = option(subparser(name), "--device")
    if device is not None:
        assert device.type is device_arg
        with pytest.raises(SystemExit):
            subparser(name).parse_args(["x", "--device", "tpu"])


@pytest.mark.parametrize("flag", ["--stage", "--precision", "--free-space", "--progress", "--mesh-format",
                                  "--t1", "--t2", "--samples", "--seed", "--max-faces", "--device"])
def test_a_shared_option_is_the_same_in_every_command(flag):
    found = {name: option(subparser(name), flag) for name in cli.COMMANDS}
    found = {k: v for k, v in found.items() if v is not None}
    assert len(found) >= 2, flag
    kinds = {(tuple(a.choices or ()), getattr(a.type, "__name__", None)) for a in found.values()}
    assert len(kinds) == 1, {k: (a.choices, a.type) for k, a in found.items()}


def test_complete_and_drive_choose_the_mesh_format_the_same_way(tmp_path):
    from hgca_core.commands.complete import output_paths
    from hgca_core.errors import InputError

    assert [p.name for p in output_paths(str(tmp_path / "m.glb"), 2)] == ["m_s0.glb", "m_s1.glb"]
    assert [p.name for p in output_paths(str(tmp_path / "m"), 1, "obj")] == ["m_s0.obj"]
    assert [p.name for p in output_paths(str(tmp_path / "m.npz"), 1, "npz")] == ["m_s0.npz"]
    with pytest.raises(InputError, match="disagrees with --mesh-format glb"):
        output_paths(str(tmp_path / "m.ply"), 1, "glb")
    with pytest.raises(InputError, match="or give --mesh-format"):
        output_paths(str(tmp_path / "m"), 1)
    for name in ("complete", "drive"):
        assert option(subparser(name), "--mesh-format").choices == ("ply", "glb", "obj", "npz")

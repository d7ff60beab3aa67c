"""The command line's surface: every option has help, `-o/--out` names the kind of thing it is, `complete` and
`drive` choose the mesh format the same way, and an option shared by commands has one definition (in
commands/arguments.py) and one type."""
from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from hgca_core import cli
from hgca_core.errors import InputError
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
    device = option(subparser(name), "--device")
    if device is not None:
        assert device.type.__name__ == "device"      # config.check_setting's kind, made by add_config_arguments
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


# Options two commands both take with a different meaning: named here, so a new clash is a decision, not drift.
DISTINCT = {"--size": "drive: the tile side; region: the box's three sides",
            "--count": "synth: samples to make; eval: samples to score",
            "--data": "train: several dataset folders; eval: the one scored",
            "--split": "synth: the split to build; eval: the split to score",
            "--workers": "drive: tiles at once (Ray); synth: processes making samples",
            "--resume": "train: continue the checkpoint; eval-real: keep the cases written"}
ARGUMENTS = Path(cli.__file__).resolve().parent / "commands" / "arguments.py"


def _defined_options(path: Path) -> list[tuple[int, str]]:
    """(line, option) of each option string an `add_argument` call in `path` spells out."""
    import ast

    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "add_argument":
            found += [(node.lineno, a.value) for a in node.args if isinstance(a, ast.Constant)
                      and isinstance(a.value, str) and a.value.startswith("-")]
    return found


def test_an_option_shared_by_commands_has_one_definition():
    """Every option two or more commands take is added by one function of commands/arguments.py (one type, one
    bound, one help to adapt), never spelled out in a command's module; arguments.py spells each out once."""
    users: dict[str, set[str]] = {}
    for name in cli.COMMANDS:
        for a in subparser(name)._actions:
            if not isinstance(a, argparse._HelpAction):
                for flag in a.option_strings:
                    users.setdefault(flag, set()).add(name)
    shared = {flag for flag, names in users.items() if len(names) > 1}
    assert set(DISTINCT) <= shared, sorted(set(DISTINCT) - shared)
    commands = ARGUMENTS.parent
    bad = [f"{f.name}:{line} defines {flag} (also in {', '.join(sorted(users[flag]))})"
           for f in sorted(commands.glob("*.py")) if f != ARGUMENTS
           for line, flag in _defined_options(f) if flag in shared - set(DISTINCT)]
    assert not bad, bad
    spelled = [flag for _, flag in _defined_options(ARGUMENTS)]
    assert len(spelled) == len(set(spelled)), sorted({f for f in spelled if spelled.count(f) > 1})


def test_completion_options_are_made_from_the_configs_fields():
    """`hgca complete` has one option per `CompletionConfig` field, with the field's help, choices and default;
    a value out of a field's bounds fails while parsing with the message the config itself gives."""
    from dataclasses import fields

    from hgca_core.config import CompletionConfig, flag_of

    p = subparser("complete")
    for f in fields(CompletionConfig):
        action = option(p, flag_of(f))
        assert action is not None and action.dest == f.name, f.name
        assert action.help.startswith(f.metadata["help"]), f.name
        assert tuple(action.choices or ()) == tuple(f.metadata["choices"]), f.name
        if f.metadata["kind"] not in ("steps", "faces"):     # those two leave the choice to the weights / the run
            assert action.default == getattr(CompletionConfig(), f.name), f.name
    for name, bad in (("samples", 0), ("samples", 1001), ("seed", -1), ("t1", 1001), ("max_faces", 999)):
        with pytest.raises(InputError) as built:
            CompletionConfig(**{name: bad})
        with pytest.raises(SystemExit):
            p.parse_args(["scan.ply", "-o", "m.ply", flag_of(next(f for f in fields(CompletionConfig)
                                                                  if f.name == name)), str(bad)])
        assert str(built.value).startswith(name + " must"), built.value


def test_a_parse_error_carries_the_configs_message(capsys):
    from hgca_core.config import CompletionConfig

    with pytest.raises(InputError) as built:
        CompletionConfig(max_faces=10)
    with pytest.raises(SystemExit):
        subparser("drive").parse_args(["scan.ply", "-o", "d", "--max-faces", "10"])
    assert str(built.value).removeprefix("max_faces ") in capsys.readouterr().err


def test_no_command_types_a_config_option_by_hand():
    """The options of `CompletionConfig` / `DriveConfig` fields are made only by `add_config_arguments`: no command
    module writes `add_argument("--samples", ...)` with a default, a bound or a help of its own."""
    import re
    from dataclasses import fields

    from hgca_core.config import CompletionConfig, DriveConfig, flag_of

    flags = {flag_of(f) for cls in (CompletionConfig, DriveConfig) for f in fields(cls)
             if f.metadata.get("kind") != "nested"} - {"--tile-memory"}   # GiB on the command line, bytes in the config
    commands = Path(cli.__file__).resolve().parent / "commands"
    for path in commands.glob("*.py"):
        typed = set(re.findall(r'add_argument\(\s*"(--[a-z0-9-]+)"', path.read_text())) & flags
        if path.name == "region.py":
            typed -= {"--size"}         # the region box's three sides, not a drive's tile side
        if path.name == "synth.py":
            typed -= {"--workers"}      # processes that build scenes, not tiles
        if path.name == "arguments.py":
            typed -= {"--seed", "--threads"}   # a training run's seed and threads, typed by the config's fields
        assert not typed, (path.name, typed)

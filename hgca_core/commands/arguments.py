"""The commands' shared options, each defined once, and the argument types and checks behind them, so a flag out
of range fails while parsing or before any work, with the flag's name, and never as an overflow or a traceback
minutes later. Defaults and bounds come from `hgca_core.config`; `completion_config` maps parsed options back to
a `CompletionConfig`, so a command maps argv to a config and calls the library.

Parsing types (`argparse` calls them) turn a bad value into `hgca CMD: error: argument --flag: ...`, exit 2.
Checks of combinations (a seed plus its samples, a stride from size and overlap) raise `InputError`.
Nothing here imports torch: parsing must stay fast.
"""
from __future__ import annotations

import argparse
import math
from dataclasses import Field, fields
from typing import Any, Callable

from hgca_core.config import (CompletionConfig, DriveConfig, check_setting, config_field,
                              flag_of, check_seed_span as _check_seed_span)
from hgca_core.errors import InputError

DEFAULTS = CompletionConfig()
PROGRESS_MODES = ("bar", "jsonl", "none")


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None


def counted(low: int, high: int | None = None) -> Callable[[str], int]:
    """A type for a count in [low, high] (`--samples`, `--workers`, `--count`, ...)."""
    def parse(text: str) -> int:
        value = _int(text)
        if value < low or (high is not None and value > high):
            span = f"at least {low}" if high is None else f"between {low} and {high}"
            raise argparse.ArgumentTypeError(f"must be {span}, got {value}")
        return value
    parse.__name__ = "count"
    return parse


def number(predicate: Callable[[float], bool], must: str) -> Callable[[str], float]:
    """A type for one finite number that satisfies `predicate` (`must` says what it must be, for the message)."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        if not math.isfinite(value) or not predicate(value):
            raise argparse.ArgumentTypeError(f"must be {must}, got {text!r}")
        return value
    parse.__name__ = "number"
    return parse


positive_float = number(lambda v: v > 0, "a finite number above 0")   # metres, GiB
finite_float = number(lambda v: True, "a finite number")                # degrees, metres that may be 0 or negative


def check_seed_span(seed: int, count: int, what: str = "samples") -> None:
    """Refuse a seed whose last use (seed + count - 1) leaves the 64-bit range, before the first sample runs."""
    try:
        _check_seed_span(seed, count, what)
    except InputError as exc:
        raise InputError(f"--{exc}") from None


def floats_arg(what: str, positive: bool = False) -> Callable[[str], list[float]]:
    """A type for comma-separated finite numbers (`--widths 40,60`); '' gives an empty list."""
    def parse(text: str) -> list[float]:
        values = []
        for part in (p.strip() for p in text.split(",")):
            if not part:
                continue
            try:
                value = float(part)
            except ValueError:
                raise argparse.ArgumentTypeError(f"{what} must be comma-separated numbers, got {part!r} in "
                                                 f"{text!r}") from None
            if not math.isfinite(value) or (positive and value <= 0):
                raise argparse.ArgumentTypeError(f"{what} must be finite{' and above 0' if positive else ''}, "
                                                 f"got {part!r}")
            values.append(value)
        return values
    parse.__name__ = "numbers"
    return parse


# -- the options of a config, made from its fields' metadata (`hgca_core.config.setting`): each option's type,
# bounds, choices, default and help are the field's, and its value is checked by the field's own check
def setting_type(f: Field) -> Callable[[str], Any]:
    """The argparse type of config field `f`: the text read as the field's kind, then `config.check_setting`, so
    a bad value fails while parsing with the config's own message (`argument --t1: must be ...`)."""
    kind = f.metadata["kind"]

    def parse(text: str) -> Any:
        if kind in ("whole", "steps", "faces"):
            value: Any = _int(text)
        elif kind == "number":
            try:
                value = float(text)
            except ValueError:
                raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        else:
            value = text.strip() if kind == "device" else text
        try:
            return check_setting(f, value)
        except InputError as exc:
            message = str(exc)
            raise argparse.ArgumentTypeError(message[len(f.name) + 1:] if message.startswith(f.name + " ")
                                             else message) from None
    parse.__name__ = kind
    return parse


def add_config_arguments(p: argparse.ArgumentParser | argparse._ActionsContainer, names: tuple[str, ...],
                         cls: type = CompletionConfig, **overrides: dict[str, Any]) -> None:
    """One option per field `names` of config class `cls`, made from the field's metadata. `overrides[name]` may
    replace the option's `help` or `default` (`hgca eval`'s 3 samples), never its bounds or choices; a help that
    names its default is shown as it is."""
    base = cls()
    for name in names:
        f = config_field(cls, name)
        m, own = f.metadata, dict(overrides.get(name, {}))
        default = own.pop("default", getattr(base, name))
        if m["kind"] in ("steps", "faces"):
            default = None                  # left out: the weights' own chain, the config's (or a tile's) faces
        given_help = "help" in own
        help = own.pop("help", m["help"])
        if own:
            raise TypeError(f"add_config_arguments: unknown override(s) {sorted(own)} of {name}")
        shown = DEFAULTS.max_faces if m["kind"] == "faces" else default
        if m["kind"] == "switch":
            if default:                     # a switch that is on: --no-NAME (its help says what turning it off does)
                p.add_argument(f"--no-{name.replace('_', '-')}", dest=name, action="store_false",
                               help=help if given_help else f"turn off: {help}")
            else:
                p.add_argument(flag_of(f), dest=name, action="store_true", help=help)
            continue
        kw: dict[str, Any] = {"dest": name, "default": default, "metavar": m["metavar"]}
        if m["choices"]:
            kw.update(choices=m["choices"], metavar=None)
        elif m["kind"] not in ("path", "address"):
            kw["type"] = setting_type(f)
        if shown is not None and m["kind"] != "steps" and "(default" not in help:
            help = f"{help} (default {shown:,})" if isinstance(shown, int) else f"{help} (default {shown})"
        p.add_argument(flag_of(f), help=help, **kw)


def completion_config(args: argparse.Namespace, base: CompletionConfig = DEFAULTS) -> CompletionConfig:
    """The `CompletionConfig` of a command's parsed options (those it has; the rest from `base`)."""
    given = {f.name: getattr(args, f.name) for f in fields(CompletionConfig) if hasattr(args, f.name)}
    if given.get("max_faces") is None:
        given.pop("max_faces", None)
    return base.with_(**given)


# A completion's options in `hgca complete` and `hgca drive` (`CompletionConfig`'s fields, in the help's order)
COMPLETION_OPTIONS = ("samples", "seed", "stage", "quality", "device", "max_faces", "precision", "t1", "t2",
                      "weights", "fine_weights", "free_space")


def add_completion_arguments(p: argparse.ArgumentParser, **overrides: dict[str, Any]) -> None:
    """The `CompletionConfig` options of `hgca complete` and `hgca drive`."""
    add_config_arguments(p, COMPLETION_OPTIONS, **overrides)


def add_noplanner_argument(p: argparse.ArgumentParser) -> None:
    """The evaluations' planner ablation (`RealEvalSettings.noplanner_weights`; not a completion setting)."""
    p.add_argument("--noplanner-weights", default=None,
                   help="GCA (no planner) weights file or training checkpoint (default: the shipped "
                        "coarse_noplanner.pt)")


def check_device(device: str) -> None:
    """`pipeline.check_device` (imports torch: call it after parsing)."""
    from hgca_core.pipeline import check_device as check

    check(device)


# `--seed` of a training run or a synthetic scene: the bounds of a completion's seed (0 to 2**63 - 1)
seed_arg = setting_type(config_field(CompletionConfig, "seed"))


def add_seed_argument(p: argparse.ArgumentParser | argparse._ActionsContainer, help: str,
                      default: int | None = DEFAULTS.seed) -> None:
    """`--seed`: of a completion's samples (the default), of a training run or of a synthetic scene (no default)."""
    p.add_argument("--seed", type=seed_arg, default=default, metavar="N",
                   help=help if default is None else f"{help} (default {default})")


def add_threads_argument(p: argparse.ArgumentParser, help: str, default: int | None = None) -> None:
    """`--threads` of training and evaluation runs, with a drive's bounds (`DriveConfig.threads`)."""
    p.add_argument("--threads", type=setting_type(config_field(DriveConfig, "threads")), default=default,
                   metavar="N", help=help)


def add_methods_argument(p: argparse.ArgumentParser, methods: tuple[str, ...], default: str | None,
                         help: str = "") -> None:
    """`--methods` of the evaluations: the rows of the table."""
    p.add_argument("--methods", default=default, help=f"comma list of {', '.join(methods)}{help}")


# The options of the commands that read scans (read, info, region, complete, drive, eval-real, poses).
def add_frames_argument(p: argparse.ArgumentParser,
                        help: str = "frames of a sequence folder, in time order (default: the 5 around the middle)"
                        ) -> None:
    p.add_argument("--frames", metavar="START:STOP[:STEP]", help=help)
    p.add_argument("--topic", metavar="TOPIC", help="a ROS bag's point cloud topic (sensor_msgs/PointCloud2; "
                                                    "default: the bag's only one)")


def add_poses_argument(p: argparse.ArgumentParser,
                       help: str = "JSON with a sensor->world 4x4 pose per scan (see docs/CONTRACTS.md)") -> None:
    p.add_argument("--poses", metavar="POSES", help=help)


def add_format_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--format", dest="fmt", metavar="FORMAT",
                   help="force the scan format (ply, las, pcd, xyz, npy, npz, kitti, nuscenes) instead of the "
                        "extension's")


def add_json_argument(p: argparse.ArgumentParser, help: str) -> None:
    """`--json`: one JSON object on stdout instead of the text (what is in it is the command's help)."""
    p.add_argument("--json", action="store_true", help=help)


def add_progress_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--progress", choices=PROGRESS_MODES, default="bar",
                   help="bar: a progress bar on stderr (default); jsonl: one JSON object per line on stdout (what "
                        "the Blender add-on reads); none: quiet")


def add_out_argument(p: argparse.ArgumentParser, metavar: str, help: str, **kw) -> None:
    """`-o/--out`, in every command that writes: a folder where the metavar is DIR (the command writes several
    files into it), else the one file's path (its metavar names the kind: MESH, FILE.npz, FILE.json)."""
    p.add_argument("-o", "--out", metavar=metavar, help=help, **kw)

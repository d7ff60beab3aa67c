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
import re
from typing import Callable

from hgca_core.config import (FREE_SPACE_MODES, MAX_SAMPLES, MAX_STEPS, MAX_THREADS, MAX_WORKERS, MESH_FORMATS,
                              MIN_FACES, QUALITIES, SEED_MAX, STAGES, CompletionConfig, check_seed_span as _check_seed_span)
from hgca_core.errors import InputError
from hgca_core.nn.precision import PRECISIONS

DEFAULTS = CompletionConfig()
PROGRESS_MODES = ("bar", "jsonl", "none")


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None


def seed_arg(text: str) -> int:
    """`--seed`: a whole number in [0, 2**63 - 1]."""
    value = _int(text)
    if not 0 <= value <= SEED_MAX:
        raise argparse.ArgumentTypeError(f"must be between 0 and 2**63 - 1 = {SEED_MAX}, got {value}")
    return value


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


samples_arg = counted(1, MAX_SAMPLES)


def max_faces_arg(text: str) -> int:
    """`--max-faces`: 0 (keep every triangle) or at least MIN_FACES."""
    value = _int(text)
    if value != 0 and value < MIN_FACES:
        raise argparse.ArgumentTypeError(f"must be 0 (keep every triangle) or at least {MIN_FACES} (max_faces), "
                                         f"got {value}")
    return value


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


def device_arg(text: str) -> str:
    """`--device`: cpu, cuda or cuda:N, checked while parsing so a typo fails before any work."""
    if re.fullmatch(r"cpu|cuda(:\d+)?", text.strip()):
        return text.strip()
    raise argparse.ArgumentTypeError(f"unknown device {text!r}: use cpu, cuda or cuda:N")


def check_device(device: str) -> None:
    """`pipeline.check_device` (imports torch: call it after parsing)."""
    from hgca_core.pipeline import check_device as check

    check(device)


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


def steps_arg(text: str) -> int:
    """`--t1` / `--t2` type: a step count in [0, MAX_STEPS], where 0 (like leaving the option out) means the
    weights' own; a bound, since each step is a pass of the network (10^9 steps would never end)."""
    value = _int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 (the weights' own step count) or more, got {value}")
    if value > MAX_STEPS:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_STEPS} steps, got {value}")
    return value


# The options of a completion (`CompletionConfig`'s fields), one definition each; `add_completion_arguments`
# adds those a command takes and `completion_config` maps them back. Defaults come from the config.
def add_stage_argument(p: argparse.ArgumentParser, help: str | None = None, quality: bool = True,
                       stages: tuple[str, ...] = STAGES) -> None:
    """`--stage` and (with `quality`) `--quality`: how far a completion goes and which shipped weights run it."""
    p.add_argument("--stage", choices=stages, default=DEFAULTS.stage,
                   help=help or f"full: 20 cm coarse GCA, 10 cm cGCA upsampling and an implicit mesh; coarse: the "
                                f"20 cm voxels only (faster); preview: the coarse cells as a smooth surface, for "
                                f"deciding where a region goes (fastest); default {DEFAULTS.stage}")
    if quality:
        p.add_argument("--quality", choices=QUALITIES, default=DEFAULTS.quality,
                       help=f"which shipped weights run when --weights / --fine-weights name none: fast = the "
                            f"few-step students (T1 10, T2 5), best = the paper's chains (T1 30, T2 15); default "
                            f"{DEFAULTS.quality} (their measured quality and speed: MODEL_CARD.md)")


def add_precision_argument(p: argparse.ArgumentParser) -> None:
    """`--precision`, shared by complete, drive, eval, eval-real and bench."""
    p.add_argument("--precision", choices=PRECISIONS, default=DEFAULTS.precision,
                   help=f"GEMM precision of the sparse convs while sampling (default {DEFAULTS.precision}: the same "
                        "mesh on any thread count; bf16 is faster where the CPU has AVX512-BF16/AMX but its mesh "
                        "may differ between thread counts; auto: bf16 where the hardware has it)")


def add_free_space_argument(p: argparse.ArgumentParser, what: str = "") -> None:
    """`--free-space`, shared by complete, drive, eval and eval-real (`config.FREE_SPACE_MODES`)."""
    p.add_argument("--free-space", choices=FREE_SPACE_MODES, default=DEFAULTS.free_space,
                   help=f"observed free space{what}: what the sensor saw through (needs sensor origins). feature = "
                        "give it to weights trained with it; mask = also never output a cell deep in it (seen-empty "
                        "cells whose six neighbours are seen empty); off = neither; auto (default) = mask where the "
                        "weights take the feature (the shipped coarse.pt, coarse_noplanner.pt and fine.pt do) and "
                        "the scans have sensor origins, nothing for weights without it")


def add_steps_arguments(p: argparse.ArgumentParser, which: tuple[str, ...] = ("t1", "t2")) -> None:
    """`--t1` and `--t2`, shared by complete, drive, eval, eval-real and bench."""
    text = {"t1": "coarse steps T1 (0 or left out: the weights' own, 30 for the shipped ones)",
            "t2": "fine steps T2 (0 or left out: the weights' own, 15 for the shipped ones)"}
    for name in which:
        p.add_argument(f"--{name}", type=steps_arg, default=None, help=text[name])


def add_device_argument(p: argparse.ArgumentParser, help: str = "cpu, cuda or cuda:N") -> None:
    p.add_argument("--device", type=device_arg, default=DEFAULTS.device, help=f"{help} (default {DEFAULTS.device})")


def add_weights_arguments(p: argparse.ArgumentParser, noplanner: bool = False) -> None:
    """`--weights` and `--fine-weights` (and the planner ablation's `--noplanner-weights` for the evaluations)."""
    p.add_argument("--weights", default=None,
                   help="coarse weights file or training checkpoint (default: the shipped coarse.pt)")
    if noplanner:
        p.add_argument("--noplanner-weights", default=None,
                       help="GCA (no planner) weights file or training checkpoint (default: the shipped "
                            "coarse_noplanner.pt)")
    p.add_argument("--fine-weights", default=None, help="fine weights file, stage full (default: the shipped fine.pt)")


def add_samples_argument(p: argparse.ArgumentParser, default: int = DEFAULTS.samples,
                         help: str = "number of completions k, one mesh each") -> None:
    p.add_argument("--samples", type=samples_arg, default=default, help=f"{help} (default {default})")


def add_seed_argument(p: argparse.ArgumentParser | argparse._ActionsContainer, help: str,
                      default: int | None = DEFAULTS.seed) -> None:
    """`--seed`: of a completion's samples (the default), of a training run or of a synthetic scene (no default)."""
    p.add_argument("--seed", type=seed_arg, default=default, metavar="N",
                   help=help if default is None else f"{help} (default {default})")


def add_semantics_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--semantics", action="store_true",
                   help="label every face with a class (road, sidewalk, building, car, tree, pole, fence, shelter, "
                        "person): a PLY face property `label`, NPZ `face_label`, one GLB primitive per class; with "
                        "--samples k also each face's class agreement across the samples. The geometry is unchanged")


def add_threads_argument(p: argparse.ArgumentParser, help: str, default: int | None = None) -> None:
    p.add_argument("--threads", type=counted(1, MAX_THREADS), default=default, metavar="N", help=help)


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


def add_completion_arguments(p: argparse.ArgumentParser, seed_help: str, max_faces_help: str | None = None,
                             free_space_what: str = "") -> None:
    """The `CompletionConfig` options of `hgca complete` and `hgca drive`."""
    add_samples_argument(p)
    add_seed_argument(p, seed_help)
    add_stage_argument(p)
    add_device_argument(p)
    p.add_argument("--max-faces", type=max_faces_arg, default=None,
                   help=max_faces_help or f"simplify each mesh to at most this many triangles (default "
                                          f"{DEFAULTS.max_faces:,}; 0 keeps every triangle: a default region's "
                                          "full-stage mesh has 1.9-3.1 M)")
    add_precision_argument(p)
    add_steps_arguments(p)
    add_weights_arguments(p)
    add_free_space_argument(p, free_space_what)


def completion_config(args: argparse.Namespace, base: CompletionConfig = DEFAULTS) -> CompletionConfig:
    """The `CompletionConfig` of a command's parsed options (those it has; the rest from `base`)."""
    names = ("stage", "samples", "seed", "t1", "t2", "weights", "fine_weights", "device", "precision", "max_faces",
             "free_space", "semantics", "semantics_weights", "quality")
    given = {n: getattr(args, n) for n in names if hasattr(args, n)}
    if given.get("max_faces") is None:
        given.pop("max_faces", None)
    return base.with_(**given)


def add_progress_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--progress", choices=PROGRESS_MODES, default="bar",
                   help="bar: a progress bar on stderr (default); jsonl: one JSON object per line on stdout (what "
                        "the Blender add-on reads); none: quiet")


def add_mesh_format_argument(p: argparse.ArgumentParser, default: str | None, help: str) -> None:
    """`--mesh-format`, shared by complete and drive (`config.MESH_FORMATS`)."""
    p.add_argument("--mesh-format", choices=MESH_FORMATS, default=default, help=help)


def add_out_argument(p: argparse.ArgumentParser, metavar: str, help: str, **kw) -> None:
    """`-o/--out`, in every command that writes: a folder where the metavar is DIR (the command writes several
    files into it), else the one file's path (its metavar names the kind: MESH, FILE.npz, FILE.json)."""
    p.add_argument("-o", "--out", metavar=metavar, help=help, **kw)

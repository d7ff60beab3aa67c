"""`hgca eval-real`: score completions of real scans without ground truth, as a table with renderings.

Measures (`hgca_core.metrics.realscan`): observed free space on the whole input, and height-cut
extrapolation (input cut h metres above the estimated ground; recall of the real cells cut away, and
generated cells above the cut in the full input's observed free space). Rows: the input itself, Open3D
Poisson, GCA without planner, hGCA coarse and hGCA full, sampled k times where they sample. Completions go
through the public `hgca_core.complete`, in the default region around the first sensor origin.
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

from hgca_core.commands.arguments import (add_config_arguments, add_frames_argument, add_methods_argument,
                                          add_noplanner_argument, add_out_argument, add_threads_argument,
                                          finite_float, setting_type)
from hgca_core.config import CompletionConfig, config_field
from hgca_core.metrics.real_eval import METHODS

# The real fixtures shipped with the repository (tests/data/real), wherever the command is run from
DEFAULT_REAL = str(Path(__file__).resolve().parents[2] / "tests" / "data" / "real")
AV2_7FAB = "av2/7fab2350-7eaf-3b7e-a39d-6937a4c1bede"
# The fixtures this project has: (name, path under --real-dir, frames, calibration for a log without one)
DEFAULT_INPUTS = (
    ("av2_7fab2350", AV2_7FAB, "0:2", None),
    ("av2_adcf7d18", "av2/adcf7d18-0510-35b0-a2fa-b4cea13a6d76", None,
     f"{AV2_7FAB}/calibration/egovehicle_SE3_sensor.feather"),
    ("nuscenes_1532402927647951", "nuscenes_lidar_top_1532402927647951.pcd.bin", None, None),
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("inputs", nargs="*", help="scan files or sequence folders (default: every real fixture in "
                                            "--real-dir: both AV2 logs and the nuScenes sweep)")
    p.add_argument("--real-dir", default=DEFAULT_REAL, help="the real fixtures folder (for the default inputs)")
    add_frames_argument(p, "frames of the sequence inputs given")
    p.add_argument("--calibration", help="AV2 egovehicle_SE3_sensor table for logs given without one")
    add_out_argument(p, "FILE.json", required=True,
                     help="results JSON; the table goes to .md beside it, renderings to <stem>_<input>*.png "
                          "(the repository's page: benchmarks/results/real_scans.json)")
    add_methods_argument(p, METHODS, ",".join(METHODS), " (default: all)")
    p.add_argument("--cuts", default="1.5,2.0", help="cut heights above the ground, metres")
    p.add_argument("--full-cuts", default="2.0", help="cut heights where the full stage runs (it is slow)")
    add_config_arguments(p, ("samples", "seed"), samples={"default": 3, "help": "k for the sampling rows"})
    p.add_argument("--full-samples", type=setting_type(config_field(CompletionConfig, "samples")), default=None,
                   help="k for the full-stage rows (default --samples)")
    p.add_argument("--yaw", type=finite_float, default=0.0, metavar="DEG",
                   help="turn each input's region by DEG degrees about the vertical (default 0: the region's axes "
                        "along the scan's frame, as `hgca complete` picks it); a model trained on regions along the "
                        "drive may score otherwise on a turned box")
    add_threads_argument(p, "torch / Open3D threads (default 1)", default=1)
    add_config_arguments(p, ("t1", "t2", "weights", "fine_weights", "precision", "free_space"))
    add_noplanner_argument(p)
    p.add_argument("--no-render", action="store_true", help="skip the PNG renderings")
    p.add_argument("--resume", action="store_true",
                   help="keep the cases an earlier run with the same sampling settings wrote to --out (a later "
                        "run may add cut levels)")


def _floats(text: str, what: str) -> list[float]:
    from hgca_core.errors import InputError

    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"{what} must be comma-separated numbers, got {text!r}") from None


def inputs_of(args: argparse.Namespace) -> list[dict]:
    """(name, source, frames, calibration) of every input, checked to exist."""
    from hgca_core.errors import InputError

    if args.inputs:
        return [{"name": Path(p.rstrip("/")).name.split(".")[0], "path": p, "frames": args.frames,
                 "calibration": args.calibration, "topic": args.topic} for p in args.inputs]
    root = Path(args.real_dir)
    if not root.is_dir():
        raise InputError("real fixtures folder not found (give --real-dir or inputs)", str(root))
    return default_items(root)


def default_items(root: str | Path) -> list[dict]:
    """The fixtures of DEFAULT_INPUTS under the real fixtures folder `root`, as `metrics.real_eval` reads an input (name,
    path, frames, calibration); the benchmarks on the real logs read them through this too."""
    root = Path(root)
    return [{"name": n, "path": str(root / p), "frames": f, "calibration": None if c is None else str(root / c)}
            for n, p, f, c in DEFAULT_INPUTS]


def run(args: argparse.Namespace) -> int:
    import torch
    from tqdm import tqdm

    from hgca_core.errors import InputError
    from hgca_core.io.atomic import atomic_write

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = set(methods) - set(METHODS)
    if unknown:
        raise InputError(f"unknown methods {sorted(unknown)}; choose from {', '.join(METHODS)}")
    cuts, full_cuts = _floats(args.cuts, "--cuts"), _floats(args.full_cuts, "--full-cuts")
    if not math.isfinite(args.yaw):
        raise InputError(f"--yaw must be a finite number of degrees, got {args.yaw}")
    if args.samples < 1 or (args.full_samples is not None and args.full_samples < 1):
        raise InputError("--samples and --full-samples must be at least 1")
    out = Path(args.out)
    from hgca_core.commands.arguments import check_seed_span
    from hgca_core.io.paths import check_outputs

    check_seed_span(args.seed, max(args.samples, args.full_samples or 0))
    check_outputs([out, out.with_suffix(".md")], [*args.inputs, args.calibration, args.weights, args.fine_weights,
                                                  args.noplanner_weights])
    torch.set_num_threads(max(1, args.threads))
    from hgca_core.models.weights import weights_record
    from hgca_core.metrics.real_eval import WAYMO_NA, evaluate_input, format_tables
    from hgca_core.config import CompletionConfig
    from hgca_core.metrics.settings import RealEvalSettings

    completion = CompletionConfig(samples=args.samples, seed=args.seed, t1=args.t1, t2=args.t2,
                                  precision=args.precision, free_space=args.free_space, weights=args.weights,
                                  fine_weights=args.fine_weights)
    settings = RealEvalSettings(completion=completion, noplanner_weights=args.noplanner_weights,
                                full_samples=args.full_samples, threads=args.threads, yaw=args.yaw)

    items = inputs_of(args)
    config = {"methods": methods, "cuts": cuts, "full_cuts": full_cuts, "samples": args.samples,
              "full_samples": args.full_samples or args.samples, "seed": args.seed, "threads": args.threads,
              "t1": args.t1, "t2": args.t2, "precision": args.precision, "free_space": args.free_space,
              "yaw_deg": args.yaw,
              **weights_record(methods, args.weights, args.fine_weights, args.noplanner_weights)}
    results = {"config": config, "inputs": {}, "waymo_protocol": {"applicable": False, "reason": WAYMO_NA}}
    earlier = _earlier(out, config) if args.resume else {}
    total = time.time() - float(earlier.get("total_seconds") or 0.0)

    def save(name: str, partial: dict) -> None:
        results["inputs"][name] = partial
        results["total_seconds"] = time.time() - total
        text = json.dumps(_finite(results), indent=1).encode()
        atomic_write(out, lambda f: f.write(text))
        md = format_tables(results).encode()
        atomic_write(out.with_suffix(".md"), lambda f: f.write(md))

    for item in tqdm(items, desc="eval-real", unit="input"):
        name = item["name"]
        res = evaluate_input(item, methods, cuts, full_cuts, settings, out, render=not args.no_render,
                             done=earlier.get("inputs", {}).get(name), saved=lambda r, n=name: save(n, r))
        save(name, res)
    print(format_tables(results))
    return 0


RESUME_KEYS = ("samples", "full_samples", "seed", "t1", "t2", "precision", "free_space",
               "weights_sha256")  # must match to resume


def _earlier(out: Path, config: dict) -> dict:
    """An earlier run's results at `out` when its sampling settings equal `config`'s (cut levels and methods
    may differ: cases are kept per cut level with the rows they have, so a later run can add levels), else an
    InputError."""
    from hgca_core.errors import InputError

    if not out.is_file():
        return {}
    try:
        old = json.loads(out.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read earlier results to resume ({exc.__class__.__name__})", str(out)) from None
    want = json.loads(json.dumps({k: config[k] for k in RESUME_KEYS}))
    have = {k: old.get("config", {}).get(k) for k in RESUME_KEYS}
    if have != want:
        raise InputError(f"earlier results were made with other settings ({have}); "
                         "run without --resume or with the same settings", str(out))
    return old


def _finite(obj):
    """JSON has no NaN: write null instead."""
    if isinstance(obj, float):
        return obj if obj == obj and abs(obj) != float("inf") else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj

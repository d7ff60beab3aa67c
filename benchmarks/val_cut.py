"""The real-scan protocol on synthetic val sweeps (run by hand): `python benchmarks/val_cut.py --weights W --out F`.

Why: the val IoU chooses coarse checkpoints on the uncut multi-scan input, and missed that a candidate grew twice as
much above a height cut, much of it in space the sensor saw empty (benchmarks/results/synth2_val_cut_38088.md). This
scores val scenes the way `hgca eval-real` scores the real logs, so a checkpoint can be checked for it before the
real logs (which are few) are spent: the first sweep of each of the first `--count` val scenes is written as an NPZ
scan with its sensor origin (the `hgca read` layout), then `hgca eval-real` completes and scores them (coarse stage,
k = `--samples`, cut heights `--cuts`). Writes F (.json) and the table beside it (.md).
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
# the `hgca` CLI in a process of its own, as a user runs it: the CLI sets torch's OpenMP policy before torch loads
CLI = [sys.executable, "-c", "import sys; from hgca_core.cli import main; sys.exit(main())"]


def first_sweeps(data: Path, split: str, count: int, profiles: Sequence[str] | None = None
                 ) -> Iterator[tuple[str, np.ndarray, np.ndarray]]:
    """(sample stem, points (N, 3) region frame, sensor origin (1, 3)) of the first sweep (scan index 0) of the first
    `count` scenes of a split (with `profiles`, of those whose seed draws one of these sensor profiles): every hit
    the sample kept, beyond the region too (format 3 on), as a real sweep holds them."""
    from hgca_core.synth.dataset import draw_recipe, sample_seed
    from hgca_core.synth.rays import input_rays
    from hgca_core.training.data import split_files

    files = split_files(str(data), split)
    if profiles:
        files = [f for f in files if draw_recipe(sample_seed(f))[0] in profiles]
    for path in files[:count]:
        with np.load(path, allow_pickle=False) as z:
            points = input_rays(z, scan=0)[0]
            origin = np.asarray(z["input_origins"], dtype=np.float64)[:1]
        yield Path(path).stem, points, origin


def write_first_sweeps(data: Path, count: int, folder: Path, profiles: Sequence[str] | None = None) -> list[Path]:
    """`first_sweeps` of the first `count` val scenes (of `profiles`) as NPZ scans with their sensor origin."""
    out = []
    for stem, points, origin in first_sweeps(data, "val", count, profiles):
        target = folder / f"{stem}_sweep0.npz"
        np.savez(target, points=points, origins=origin, origin_index=np.zeros(len(points), np.int64))
        out.append(target)
    return out


def command(weights: str | Path, out: str | Path, data: str, samples: int, count: int = 4, yaw: float = 0.0,
            threads: int = 1) -> list[str]:
    """This script's command line, as the benchmarks that run it in subprocesses (keep_sweep, screen) build it."""
    return [sys.executable, str(Path(__file__).resolve()), "--data", data, "--count", str(count), "--samples",
            str(samples), "--threads", str(threads), "--yaw", f"{yaw:g}", "--weights", str(weights), "--out", str(out)]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=str(REPO / "data" / "synth2"), help="dataset folder with a val split")
    p.add_argument("--count", type=int, default=4, help="val scenes")
    p.add_argument("--weights", default=None, help="coarse weights (default: the shipped coarse.pt)")
    p.add_argument("--samples", type=int, default=3)
    p.add_argument("--cuts", default="2.0")
    p.add_argument("--profiles", default="", help="comma list: only val scenes of these sensor profiles (e.g. "
                   "av2,hdl32, the real logs' sensors; default every scene; freespace_calibration.md shows how much "
                   "the above-cut share depends on the profile)")
    p.add_argument("--yaw", type=float, default=0.0,
                   help="turn the scored region this many degrees about the sensor (`hgca eval-real --yaw`): the "
                        "synthetic streets run along the region's x axis, as the nuScenes street does, while the AV2 "
                        "streets cross the city-frame grid at -32 and 19 deg (violation_anatomy_s21_shipped.md)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", required=True, help="results JSON (the table goes to .md beside it)")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        profiles = [v.strip() for v in args.profiles.split(",") if v.strip()]
        scans = write_first_sweeps(Path(args.data), args.count, Path(tmp), profiles)
        if not scans:
            print(f"no val scenes of {profiles or 'any profile'} in {args.data}", file=sys.stderr)
            return 2
        cmd = [*CLI, "eval-real", "--threads", str(args.threads), "--methods", "hgca", "--samples", str(args.samples),
               "--cuts", args.cuts, "--no-render", *(["--weights", args.weights] if args.weights else []),
               "--yaw", str(args.yaw), "--out", args.out, *map(str, scans)]
        return subprocess.run(cmd, check=False).returncode


if __name__ == "__main__":
    sys.exit(main())

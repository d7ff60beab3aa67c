"""`hgca synth`: one synthetic street scene with its files, or a whole dataset split.

    hgca synth --seed S [--scans N] [--profile P] [--style city|suburb|town|strip] [--generator 6|7] --out DIR
    hgca synth --split train|val|test --count N --out DIR [--scans N] [--workers 2] [--generator 6|7]
    hgca synth --pack DATASET --out DIR   (the coarse stage's 20 cm cells only, ~60 kB a scene: hgca_core.dataset.packed)

Each sample draws its sensor profile and number of scans (1-10) from its seed unless given.
"""
from __future__ import annotations

import argparse
import json
import time

from hgca_core.commands.arguments import add_out_argument, add_seed_argument, counted
from hgca_core.config import MAX_WORKERS
from hgca_core.errors import InputError
from hgca_core.synth.lidar import PROFILES
from hgca_core.synth.scene import GENERATOR_VERSION, STYLE_DRAWS, STYLES


def add_arguments(p: argparse.ArgumentParser) -> None:
    what = p.add_mutually_exclusive_group(required=True)
    add_seed_argument(what, "make the scene named by this seed and write its files", default=None)
    what.add_argument("--split", choices=("train", "val", "test"),
                      help="build a dataset split (seeds: train i, val 1,000,000 + i, test 2,000,000 + i)")
    what.add_argument("--pack", metavar="DATASET",
                      help="pack a built dataset's splits for coarse training only (input, ground truth and free "
                           "space as 20 cm bit grids, ~60 kB a scene instead of ~6 MB), e.g. to carry it to a GPU "
                           "machine; resumable, like --split")
    p.add_argument("--count", type=counted(1, 10_000_000), help="samples in the split (with --split)")
    p.add_argument("--first", type=counted(0, 10**9), default=0, metavar="I",
                   help="with --split: start at the split's I-th seed (a folder of new scenes beside an older "
                        "dataset, so the two share no seed; default 0)")
    p.add_argument("--scans", type=counted(1, 255), help="input scans per sample: the ego scan + others (default: the seed "
                   "draws 1 to 10)")
    p.add_argument("--profile", choices=sorted(PROFILES),
                   help="sensor profile with --seed (default: the seed picks): " + ", ".join(
                       f"{k} ({v.dataset})" for k, v in sorted(PROFILES.items())))
    p.add_argument("--style", choices=STYLES, help="scene style (default: the seed picks)")
    p.add_argument("--generator", type=int, choices=sorted(STYLE_DRAWS),
                   help=f"scene generator version (default: a split folder's own, else {GENERATOR_VERSION}); 6 makes "
                        "every seed's scene as it was before the strip style (synth2, docs/data/synth2_recipe.json)")
    p.add_argument("--workers", type=counted(1, MAX_WORKERS), default=2, help="processes for --split (default 2)")
    p.add_argument("--no-preview", action="store_true", help="skip the preview PNG (with --seed)")
    p.add_argument("--quick", action="store_true",
                   help="smoke-test density: a quarter of the azimuth steps and sparser ground truth (not for training)")
    add_out_argument(p, "DIR", required=True, help="output folder")


def run(args: argparse.Namespace) -> int:
    from hgca_core.io.paths import check_output_folder

    check_output_folder(args.out, [args.pack])
    if args.pack is not None:
        return _pack(args)
    if args.scans is not None and not 1 <= args.scans <= 255:
        raise InputError(f"--scans must be between 1 and 255, got {args.scans}")
    if args.split is not None:
        if args.profile is not None:
            raise InputError("--profile applies to --seed only; a split draws each sample's profile from its seed")
        return _split(args)
    if args.count is not None or args.first:
        raise InputError("--count and --first go with --split, not --seed")
    if args.seed < 0:
        raise InputError(f"--seed must be non-negative, got {args.seed}")
    from hgca_core.synth.dataset import DEFAULT_QUALITY, QUICK_QUALITY, simulate
    from hgca_core.synth.export import write_scene

    t0 = time.perf_counter()
    generator = GENERATOR_VERSION if args.generator is None else args.generator
    if args.style is not None and args.style not in STYLE_DRAWS[generator][0]:
        raise InputError(f"--style {args.style} does not exist in generator version {generator}")
    sim = simulate(args.seed, args.scans, args.style, quality=QUICK_QUALITY if args.quick else DEFAULT_QUALITY,
                   profile=args.profile, generator=generator)
    t1 = time.perf_counter()
    paths = write_scene(sim, args.out, preview=not args.no_preview)
    t2 = time.perf_counter()
    s = sim.sample
    meta = json.loads(str(s["meta"]))
    print(f"scene {args.seed} ({sim.scene.style}): {len(sim.scene.mesh.faces):,} faces, {meta['n_scans']} scans "
          f"by {meta['profile']} ({meta['dataset']}), "
          f"{len(s['input_points']):,} input points in the region, {len(s['gt_occ20']):,} occupied 20 cm cells")
    print(f"simulated in {t1 - t0:.1f} s, files written in {t2 - t1:.1f} s:")
    for p in paths:
        print(f"  {p}")
    return 0


def _split(args: argparse.Namespace) -> int:
    if args.count is None or args.count < 1:
        raise InputError("--split needs --count N (N >= 1)")
    if args.style is not None:
        raise InputError("--style applies to --seed only; a split mixes styles by seed")
    if args.workers < 1:
        raise InputError(f"--workers must be at least 1, got {args.workers}")
    from hgca_core.synth.dataset import DEFAULT_QUALITY, QUICK_QUALITY
    from hgca_core.synth.splits import build_split

    t0 = time.perf_counter()
    paths = build_split(args.out, args.split, args.count, n_scans=args.scans, workers=args.workers,
                        quality=QUICK_QUALITY if args.quick else DEFAULT_QUALITY, first=args.first,
                        generator=args.generator)
    print(f"{args.split}: {len(paths)} samples in {args.out}/{args.split} ({time.perf_counter() - t0:.1f} s)")
    return 0


def _pack(args: argparse.Namespace) -> int:
    given = [f for f, v in (("--count", args.count), ("--first", args.first), ("--scans", args.scans),
                            ("--profile", args.profile), ("--style", args.style), ("--generator", args.generator),
                            ("--quick", args.quick)) if v]
    if given:
        raise InputError(f"{', '.join(given)} make scenes; --pack only packs a built dataset")
    from tqdm import tqdm

    from hgca_core.training.pack import pack_dataset

    t0 = time.perf_counter()
    bar = tqdm(desc="pack", unit="sample")

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    try:
        paths = pack_dataset(args.pack, args.out, progress=progress)
    finally:
        bar.close()
    size = sum(p.stat().st_size for p in paths)
    print(f"packed {len(paths)} samples into {args.out} ({size / 2**20:.1f} MiB, {size / max(len(paths), 1) / 1e3:.0f} kB "
          f"a sample, {time.perf_counter() - t0:.1f} s)")
    return 0

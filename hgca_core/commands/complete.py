"""`hgca complete SCAN... -o OUT.ext`: one mesh per sample, written atomically as OUT_s<i>.ext."""
from __future__ import annotations

import argparse
from pathlib import Path

from hgca_core.commands.arguments import (MAX_STEPS, check_device, check_seed_span, device_arg, max_faces_arg,
                                          samples_arg, seed_arg)
from hgca_core.errors import InputError
from hgca_core.nn.precision import DEFAULT_PRECISION, PRECISIONS

__all__ = ["device_arg", "steps_arg", "add_arguments", "run", "output_paths"]

MESH_EXTS = (".ply", ".obj", ".glb", ".npz")


def add_arguments(p: argparse.ArgumentParser) -> None:
    from hgca_core.commands.read import add_frames_argument

    p.add_argument("scans", nargs="+", help="scan files (ply, las/laz, pcd, xyz/csv, npy/npz, KITTI .bin, nuScenes "
                                            ".pcd.bin, AV2 .feather) or one sequence folder (KITTI, AV2, nuScenes)")
    add_frames_argument(p)
    p.add_argument("-o", "--out", required=True, help="output path; sample i goes to OUT_s<i>.ext (ply, obj, glb, npz)")
    p.add_argument("--poses", help="JSON with a sensor->world 4x4 pose per scan")
    p.add_argument("--format", dest="fmt", help="force the scan format instead of guessing from the extension")
    p.add_argument("--region", help="cx,cy,cz,sx,sy,sz[,yaw_deg] in the world frame (default: 38.4 x 38.4 x 8 m "
                                    "around the first scan's sensor, from 1 m below the ground)")
    p.add_argument("--samples", type=samples_arg, default=1, help="number of completions k (each its own mesh)")
    p.add_argument("--seed", type=seed_arg, default=0, help="sample i uses seed + i: same seed, same mesh")
    p.add_argument("--stage", choices=("coarse", "full"), default="full",
                   help="full (default): 20 cm coarse GCA, 10 cm cGCA upsampling and an implicit mesh; "
                        "coarse: the 20 cm voxels only (faster)")
    p.add_argument("--device", type=device_arg, default="cpu", help="cpu, cuda or cuda:N")
    p.add_argument("--max-faces", type=max_faces_arg, default=None,
                   help="simplify each mesh to at most this many triangles (default 1,000,000; 0 keeps every "
                        "triangle: a default region's full-stage mesh has ~2 M)")
    add_precision_argument(p)
    add_steps_arguments(p)
    p.add_argument("--weights", default=None, help="coarse weights file (default: the shipped ones)")
    p.add_argument("--fine-weights", default=None, help="fine weights file (default: the shipped ones)")
    p.add_argument("--progress", choices=("bar", "jsonl", "none"), default="bar")
    add_free_space_argument(p)


def add_free_space_argument(p: argparse.ArgumentParser, what: str = "") -> None:
    """`--free-space`, shared by complete, drive, eval and eval-real. The choices are
    `hgca_core.pipeline.FREE_SPACE_MODES`, spelt out so that parsing arguments does not import torch."""
    p.add_argument("--free-space", choices=("auto", "feature", "mask", "off"), default="auto",
                   help=f"observed free space{what}: what the sensor saw through (needs sensor origins). feature = "
                        "give it to weights trained with it; mask = also never output a cell deep in it (seen-empty "
                        "cells whose six neighbours are seen empty); off = "
                        "neither; auto (default) = mask where the weights take the feature (the shipped coarse.pt, "
                        "coarse_noplanner.pt and fine.pt do) and the scans have sensor origins, nothing for "
                        "weights without it")


def add_precision_argument(p: argparse.ArgumentParser) -> None:
    """`--precision`, shared by complete, drive, eval and bench (names from the torch-free
    `hgca_core.nn.precision`)."""
    p.add_argument("--precision", choices=PRECISIONS, default=DEFAULT_PRECISION,
                   help="GEMM precision of the sparse convs while sampling (default fp32: the same mesh on any "
                        "thread count; bf16 is faster where the CPU has AVX512-BF16/AMX but its mesh may differ "
                        "between thread counts; auto: bf16 where the hardware has it)")


def steps_arg(text: str) -> int:
    """`--t1` / `--t2` type: a step count in [0, MAX_STEPS], where 0 (like leaving the option out) means the
    weights' own; a bound, since each step is a pass of the network (10^9 steps would never end)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 (the weights' own step count) or more, got {value}")
    if value > MAX_STEPS:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_STEPS} steps, got {value}")
    return value


def add_steps_arguments(p: argparse.ArgumentParser) -> None:
    """`--t1` and `--t2`, shared by complete, eval and bench."""
    p.add_argument("--t1", type=steps_arg, default=None,
                   help="coarse steps T1 (0 or left out: the weights' own, 30 for the shipped ones)")
    p.add_argument("--t2", type=steps_arg, default=None,
                   help="fine steps T2 (0 or left out: the weights' own, 15 for the shipped ones)")


def output_paths(out: str, samples: int) -> list[Path]:
    """OUT_s<i>.ext for each sample (the names every sample's mesh is written to)."""
    path = Path(out)
    if path.suffix.lower() not in MESH_EXTS:
        raise InputError(f"output must end in one of {', '.join(MESH_EXTS)}", out)
    return [path.with_name(f"{path.stem}_s{i}{path.suffix}") for i in range(samples)]


def run(args: argparse.Namespace) -> int:
    from hgca_core.progress import Progress

    progress = Progress(args.progress, samples=args.samples)
    try:
        outputs = _run(args, progress)
    except InputError as exc:
        progress.error(str(exc))
        raise
    except Exception as exc:  # the add-on must hear about every failure, not only bad input
        progress.error(f"{exc.__class__.__name__}: {exc}")
        raise
    progress.done([str(p) for p in outputs])
    return 0


def _run(args: argparse.Namespace, progress) -> list[Path]:
    from hgca_core.geometry.region import Region
    from hgca_core.commands.memory import check_read_memory
    from hgca_core.io.paths import check_outputs
    from hgca_core.pipeline import check_memory

    paths = output_paths(args.out, args.samples)
    check_seed_span(args.seed, args.samples)
    check_outputs(paths, [*args.scans, args.poses, args.weights, args.fine_weights])
    check_device(args.device)
    check_read_memory(args.scans)
    region_arg = Region.parse(args.region) if args.region else None
    if region_arg is not None:
        check_memory(region_arg)

    from hgca_core.io import write_mesh, write_mesh_npz
    from hgca_core.io.atomic import AtomicBatch
    from hgca_core.io.sequence import read_inputs
    from hgca_core.pipeline import complete, load_models

    load_models(args.stage, args.weights, args.fine_weights, args.device)   # bad weights fail before any work;
    # complete() gets the same models again from the cache
    progress("read", 0, 1, f"{len(args.scans)} scan(s)", 0)
    scan = read_inputs(args.scans, poses=args.poses, fmt=args.fmt, frames=args.frames)
    progress("read", 1, 1, f"{len(scan.points)} points", 0)
    region = region_arg
    index = None
    if scan.origins is not None and len(scan.origins) and args.free_space != "off":
        from hgca_core.geometry.freespace import ray_origins

        index = ray_origins(scan.origins, scan.attributes, scan.points)
    results = complete(scan.points, region=region, origins=scan.origins, samples=args.samples, seed=args.seed,
                       stage=args.stage, device=args.device, t1=args.t1, t2=args.t2, weights=args.weights,
                       fine_weights=args.fine_weights, progress=progress, precision=args.precision,
                       max_faces=args.max_faces, origin_index=index, free_space=args.free_space)
    with AtomicBatch() as batch:  # every sample or none: an interrupted write leaves nothing behind
        for i, (res, path) in enumerate(zip(results, paths)):
            progress("write", i, len(paths), path.name, i)
            if path.suffix.lower() == ".npz":
                write_mesh_npz(path, res.mesh.vertices, res.mesh.faces, res.observed_distance, batch=batch,
                               normals=res.mesh.vertex_normals,
                               face_material=res.mesh.face_attributes.get("material"))
            else:
                write_mesh(path, res.mesh, batch=batch)
        batch.commit()
    progress("write", len(paths), len(paths), "", len(paths) - 1)
    return paths

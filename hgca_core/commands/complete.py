"""`hgca complete SCAN... -o MESH`: one mesh per sample, written atomically as MESH_s<i>.<format>."""
from __future__ import annotations

import argparse
from pathlib import Path

from hgca_core.commands.arguments import (MESH_FORMATS, add_completion_arguments, add_format_argument,
                                          add_frames_argument, add_mesh_format_argument, add_poses_argument,
                                          add_semantics_argument,
                                          add_out_argument, add_precision_argument, add_progress_argument,
                                          check_device, completion_config, device_arg, steps_arg)
from hgca_core.errors import InputError

__all__ = ["device_arg", "steps_arg", "add_arguments", "add_precision_argument", "run", "output_paths",
           "mesh_format"]

MESH_EXTS = tuple("." + f for f in MESH_FORMATS)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scans", nargs="+", help="scan files (ply, las/laz, pcd, xyz/csv, npy/npz, KITTI .bin, nuScenes "
                                            ".pcd.bin, AV2 .feather) or one sequence folder (KITTI, AV2, nuScenes)")
    add_frames_argument(p)
    add_out_argument(p, "MESH", required=True,
                     help="the mesh file's name; sample i goes to MESH_s<i>.<format>, the format from "
                          "--mesh-format or else MESH's extension (.ply, .obj, .glb, .npz)")
    add_mesh_format_argument(p, None, "mesh format (default: MESH's extension)")
    add_poses_argument(p)
    add_format_argument(p)
    p.add_argument("--region", help="cx,cy,cz,sx,sy,sz[,yaw_deg] in the world frame (default: 38.4 x 38.4 x 8 m "
                                    "around the first scan's sensor, from 1 m below the ground)")
    add_completion_arguments(p, "sample i uses seed + i: same seed, same mesh")
    add_semantics_argument(p)
    p.add_argument("--semantics-weights", default=None, help="semantic head weights (default: the shipped "
                                                             "semantics.pt); implies --semantics")
    add_progress_argument(p)


def mesh_format(out: str, asked: str | None) -> str:
    """The mesh format of `hgca complete -o out [--mesh-format asked]`: the one asked for, else the extension's;
    an extension that is a mesh format and disagrees with the one asked for is refused."""
    ext = Path(out).suffix.lower()
    if asked is None:
        if ext not in MESH_EXTS:
            raise InputError(f"output must end in one of {', '.join(MESH_EXTS)} (or give --mesh-format)", out)
        return ext[1:]
    if ext in MESH_EXTS and ext[1:] != asked:
        raise InputError(f"the output's extension {ext} disagrees with --mesh-format {asked}", out)
    return asked


def output_paths(out: str, samples: int, fmt: str | None = None) -> list[Path]:
    """MESH_s<i>.<format> for each sample (the names every sample's mesh is written to)."""
    path = Path(out)
    fmt = mesh_format(out, fmt)
    stem = path.stem if path.suffix.lower() in MESH_EXTS else path.name
    return [path.with_name(f"{stem}_s{i}.{fmt}") for i in range(samples)]


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

    config = completion_config(args)
    paths = output_paths(args.out, config.samples, args.mesh_format)
    if config.semantics_weights is not None and not config.semantics:
        config = config.with_(semantics=True)
    check_outputs(paths, [*args.scans, args.poses, config.weights, config.fine_weights, config.semantics_weights])
    check_device(config.device)
    check_read_memory(args.scans)
    region_arg = Region.parse(args.region) if args.region else None
    if region_arg is not None:
        check_memory(region_arg)

    from hgca_core.io import write_mesh, write_mesh_npz
    from hgca_core.io.atomic import AtomicBatch
    from hgca_core.io.sequence import read_inputs
    from hgca_core.pipeline import complete, load_models

    if config.semantics:
        from hgca_core.models.weights import load_semantics

        load_semantics(config.semantics_weights, config.device)
    load_models(config.stage, config.coarse_file(), config.fine_file(), config.device)   # bad weights fail before any
    # work; complete() gets the same models again from the cache
    progress("read", 0, 1, f"{len(args.scans)} scan(s)", 0)
    scan = read_inputs(args.scans, poses=args.poses, fmt=args.fmt, frames=args.frames)
    progress("read", 1, 1, f"{len(scan.points)} points", 0)
    index = None
    if scan.origins is not None and len(scan.origins) and config.free_space != "off":
        from hgca_core.geometry.freespace import ray_origins

        index = ray_origins(scan.origins, scan.attributes, scan.points)
    results = complete(scan.points, region=region_arg, origins=scan.origins, config=config, progress=progress,
                       origin_index=index)
    with AtomicBatch() as batch:  # every sample or none: an interrupted write leaves nothing behind
        for i, (res, path) in enumerate(zip(results, paths)):
            progress("write", i, len(paths), path.name, i)
            if path.suffix.lower() == ".npz":
                write_mesh_npz(path, res.mesh.vertices, res.mesh.faces, res.observed_distance, batch=batch,
                               normals=res.mesh.vertex_normals,
                               face_material=res.mesh.face_attributes.get("material"),
                               face_label=res.mesh.face_attributes.get("label"),
                               face_label_agreement=res.mesh.face_attributes.get("label_agreement"))
            else:
                write_mesh(path, res.mesh, batch=batch)
        batch.commit()
    progress("write", len(paths), len(paths), "", len(paths) - 1)
    return paths

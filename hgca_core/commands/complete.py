"""`hgca complete SCAN... -o OUT.ext`: one mesh per sample, written atomically as OUT_s<i>.ext."""
from __future__ import annotations

import argparse
from pathlib import Path

from hgca_core.errors import InputError

MESH_EXTS = (".ply", ".obj", ".glb", ".npz")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scans", nargs="+", help="scan files (ply, las/laz, pcd, xyz/csv, npy/npz, KITTI .bin, nuScenes .pcd.bin)")
    p.add_argument("-o", "--out", required=True, help="output path; sample i goes to OUT_s<i>.ext (ply, obj, glb, npz)")
    p.add_argument("--poses", help="JSON with a sensor->world 4x4 pose per scan")
    p.add_argument("--format", dest="fmt", help="force the scan format instead of guessing from the extension")
    p.add_argument("--region", help="cx,cy,cz,sx,sy,sz[,yaw_deg] in the world frame (default: 38.4 x 38.4 x 8 m "
                                    "around the first scan's sensor, from 1 m below the ground)")
    p.add_argument("--samples", type=int, default=1, help="number of completions k (each its own mesh)")
    p.add_argument("--seed", type=int, default=0, help="sample i uses seed + i: same seed, same mesh")
    p.add_argument("--stage", choices=("coarse", "full"), default="coarse",
                   help="coarse: 20 cm voxels only; full: + 10 cm cGCA upsampling and an implicit mesh")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--max-faces", type=int, default=None,
                   help="simplify each mesh to at most this many triangles (default 1,000,000; 0 keeps every "
                        "triangle: a default region's full-stage mesh has ~2 M)")
    add_precision_argument(p)
    p.add_argument("--t1", type=int, default=None, help="coarse steps T1 (default from the weights: 30)")
    p.add_argument("--t2", type=int, default=None, help="fine steps T2 (default 15)")
    p.add_argument("--weights", default=None, help="coarse weights file (default: the shipped ones)")
    p.add_argument("--fine-weights", default=None, help="fine weights file (default: the shipped ones)")
    p.add_argument("--progress", choices=("bar", "jsonl", "none"), default="bar")


def add_precision_argument(p: argparse.ArgumentParser) -> None:
    """`--precision`, shared by complete, eval and bench. The choices are `hgca_core.nn.conv.PRECISIONS`, spelt
    out so that parsing arguments does not import torch (a test holds the two equal)."""
    p.add_argument("--precision", choices=("auto", "fp32", "bf16"), default="auto",
                   help="GEMM precision of the sparse convs while sampling (auto: bf16 where the hardware has it)")


def output_paths(out: str, samples: int) -> list[Path]:
    path = Path(out)
    if path.suffix.lower() not in MESH_EXTS:
        raise InputError(f"output must end in one of {', '.join(MESH_EXTS)}", out)
    if not path.parent.exists():
        raise InputError("output folder does not exist", str(path.parent))
    return [path.with_name(f"{path.stem}_s{i}{path.suffix}") for i in range(samples)]


def run(args: argparse.Namespace) -> int:
    from hgca_core.progress import Progress

    progress = Progress(args.progress)
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
    from hgca_core.io import read_scans, write_mesh, write_mesh_npz
    from hgca_core.pipeline import complete

    if args.device.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            raise InputError("--device cuda asked for, but this torch build sees no CUDA GPU")
    paths = output_paths(args.out, args.samples)
    progress("read", 0, 1, f"{len(args.scans)} scan(s)")
    scan = read_scans(args.scans, poses=args.poses, fmt=args.fmt)
    progress("read", 1, 1, f"{len(scan.points)} points")
    region = Region.parse(args.region) if args.region else None
    results = complete(scan.points, region=region, origins=scan.origins, samples=args.samples, seed=args.seed,
                       stage=args.stage, device=args.device, t1=args.t1, t2=args.t2, weights=args.weights,
                       fine_weights=args.fine_weights, progress=progress, precision=args.precision,
                       max_faces=args.max_faces)
    for i, (res, path) in enumerate(zip(results, paths)):
        progress("write", i, len(paths), path.name)
        if path.suffix.lower() == ".npz":
            write_mesh_npz(path, res.mesh.vertices, res.mesh.faces, res.observed_distance,
                           normals=res.mesh.vertex_normals, face_material=res.mesh.face_attributes.get("material"))
        else:
            write_mesh(path, res.mesh)
    progress("write", len(paths), len(paths), "")
    return paths

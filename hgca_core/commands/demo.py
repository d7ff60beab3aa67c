"""`hgca demo`: complete the bundled example (5 simulated scans) with the shipped weights and render it."""
from __future__ import annotations

import argparse
import time
from pathlib import Path

EXAMPLE_DIR = Path(__file__).resolve().parents[1] / "examples"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from hgca_core.commands.arguments import add_config_arguments, add_out_argument, add_progress_argument

    add_out_argument(p, "DIR", required=True,
                     help="folder for the meshes (completion_s<i>.ply) and their renderings (`make demo`: demo_out)")
    add_config_arguments(p, ("samples", "seed", "stage", "quality", "semantics"))
    add_progress_argument(p)


def run(args: argparse.Namespace) -> int:
    import json

    import numpy as np

    from hgca_core.commands.complete import add_arguments as complete_arguments, run as complete_run
    from hgca_core.errors import InputError
    from hgca_core.io import read_scans
    from hgca_core.io.poses import load_poses
    from hgca_core.render import render_mesh

    poses = EXAMPLE_DIR / "poses.json"
    if not poses.exists():
        raise InputError("the bundled example is missing from the installed package", str(poses))
    scans = [str(EXAMPLE_DIR / e.file) for e in load_poses(poses)]
    # the ego-aligned box, stored as `Region.as_tuple()`: the --region form, yaw in degrees
    region = ",".join(f"{v:.6f}" for v in json.loads(poses.read_text())["region"])
    from hgca_core.commands.arguments import check_seed_span
    from hgca_core.io.paths import check_output_folder, check_outputs

    stage = args.stage
    out_dir = Path(args.out)
    check_seed_span(args.seed, args.samples)
    check_output_folder(out_dir, [EXAMPLE_DIR])
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder ({exc.strerror})", str(out_dir)) from None
    mesh_path = out_dir / "completion.ply"
    check_outputs([out_dir / f"completion_s{i}{e}" for i in range(args.samples) for e in (".ply", ".png")],
                  [EXAMPLE_DIR])
    t0 = time.time()
    parser = argparse.ArgumentParser()   # complete's own parser: its defaults, present and future, apply here too
    complete_arguments(parser)
    complete_run(parser.parse_args([*scans, "-o", str(mesh_path), f"--poses={poses}", f"--region={region}",
                                    f"--samples={args.samples}", f"--seed={args.seed}", f"--stage={stage}",
                                    f"--progress={args.progress}", *(["--semantics"] if args.semantics else [])]))
    seconds = time.time() - t0
    from plyfile import PlyData
    import trimesh

    inp = read_scans(scans, poses=str(poses)).points
    for i in range(args.samples):
        path = mesh_path.with_name(f"completion_s{i}.ply")
        ply = PlyData.read(str(path))
        v = ply["vertex"]
        verts = np.c_[v["x"], v["y"], v["z"]].astype(np.float64)
        faces = np.vstack(ply["face"]["vertex_indices"]) if ply["face"].count else np.zeros((0, 3), int)
        mesh = trimesh.Trimesh(verts, faces, process=False)
        png = path.with_suffix(".png")
        render_mesh(mesh, png, points=inp, colour_by=np.asarray(v["observed_distance"]))
        print(f"wrote {path} ({len(faces)} triangles) and {png}")
    print(f"stage {stage}: completion took {seconds:.1f} s")
    return 0

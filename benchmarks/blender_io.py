"""Blender add-on I/O speed: importing a 1M-point scan and inserting a 1M-triangle completion mesh.

    .venv/bin/python benchmarks/blender_io.py [--points 1000000] [--triangles 1000000] [--repeat 3]

Runs in the bpy module with the add-on's own code paths: `import_scans.import_scans` (the import
operator's body: `hgca read` in a subprocess, .npz load, vertex-only mesh + attributes via foreach_set)
and `mesh_build.build_results` (the job's "done" step: .npz load and checks, triangle mesh with edges,
observed_distance attribute, material, collection). Results go to benchmarks/results/blender_io.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="hgca_bench_user_"))

import bpy  # noqa: E402
import numpy as np  # noqa: E402

from hgca_blender import preferences  # noqa: E402
from hgca_blender.operators import import_scans  # noqa: E402
from hgca_blender.scene import mesh_build  # noqa: E402


def write_scan_ply(path: Path, n: int, seed: int = 0) -> None:
    """A binary little-endian PLY with x, y, z, intensity: a street-like cloud of `n` points."""
    rng = np.random.default_rng(seed)
    pts = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])
    pts["x"], pts["y"] = rng.uniform(-40, 40, n), rng.uniform(-40, 40, n)
    pts["z"] = rng.normal(-1.8, 0.05, n) + (rng.random(n) < 0.3) * rng.uniform(0, 8, n)
    pts["intensity"] = rng.random(n)
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
              "property float intensity\nend_header\n")
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(pts.tobytes())


def write_scan_npz(path: Path, n: int, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    pts = np.c_[rng.uniform(-40, 40, (n, 2)), rng.normal(-1.8, 0.05, n)].astype(np.float32)
    np.savez(path, points=pts, intensity=rng.random(n).astype(np.float32))


def write_result_npz(path: Path, triangles: int) -> tuple[int, int]:
    """A wavy height-field mesh with `triangles` faces in the completion .npz format."""
    side = int(np.ceil(np.sqrt(triangles / 2)))
    xs = np.linspace(0, 38.4, side + 1, dtype=np.float32)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    gz = np.sin(gx) * np.cos(gy)
    vertices = np.c_[gx.ravel(), gy.ravel(), gz.ravel()].astype(np.float32)
    idx = np.arange((side + 1) ** 2, dtype=np.int32).reshape(side + 1, side + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.c_[a, b, c], np.c_[a, c, d]])[:triangles]
    observed = np.abs(gz.ravel()).astype(np.float32)
    np.savez(path, vertices=vertices, faces=faces.astype(np.int32), observed_distance=observed)
    return len(vertices), len(faces)


def timed(fn, repeat: int) -> list[float]:
    out = []
    for _ in range(repeat):
        bpy.ops.wm.read_homefile(use_empty=True)
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--triangles", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--python", default=None, help="core interpreter (default: auto-detect)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "blender_io"))
    args = ap.parse_args(argv)
    python = args.python or preferences.detect_python() or sys.executable
    work = Path(tempfile.mkdtemp(prefix="hgca_bench_"))
    results: dict = {"bpy": bpy.app.version_string, "python": platform.python_version(),
                     "cpus": os.cpu_count(), "machine": platform.machine(), "repeat": args.repeat,
                     "load_avg_start": round(os.getloadavg()[0], 2)}

    for fmt, writer in (("ply", write_scan_ply), ("npz", write_scan_npz)):
        scan = work / f"scan_{args.points}.{fmt}"
        writer(scan, args.points)
        # the core's read alone (subprocess start + parse + write .npz), to split the import time
        t_read = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            import_scans.read_scans(python, [scan])
            t_read.append(time.perf_counter() - t0)

        def do_import() -> None:
            obj, *_ = import_scans.import_scans(python, [scan], bpy.context.scene.collection)
            assert len(obj.data.vertices) == args.points

        t_import = timed(do_import, args.repeat)
        pts, attrs, *_ = import_scans.read_scans(python, [scan])

        def do_build() -> None:
            mesh_build.build_point_object("scan", pts, attrs, bpy.context.scene.collection)

        t_build = timed(do_build, args.repeat)
        results[f"import_{fmt}"] = {
            "points": args.points, "file_mb": round(scan.stat().st_size / 1e6, 1),
            "total_s": round(statistics.median(t_import), 3),
            "core_read_s": round(statistics.median(t_read), 3),
            "blender_build_s": round(statistics.median(t_build), 3),
            "all_total_s": [round(t, 3) for t in t_import],
        }
        print(f"import {fmt}: {results[f'import_{fmt}']}", flush=True)

    result_npz = work / "out_s0.npz"
    n_verts, n_faces = write_result_npz(result_npz, args.triangles)
    t_insert = timed(lambda: mesh_build.build_results(bpy.context.scene, [result_npz], "hGCA bench"), args.repeat)
    arrays = mesh_build.read_result(result_npz)
    t_mesh = timed(lambda: mesh_build.triangle_mesh("m", arrays.vertices, arrays.faces), args.repeat)

    def pydata() -> None:
        me = bpy.data.meshes.new("p")
        me.from_pydata(arrays.vertices.tolist(), [], arrays.faces.tolist())
        me.update(calc_edges=True)

    t_pydata = timed(pydata, 1)
    results["insert_mesh"] = {
        "vertices": n_verts, "triangles": n_faces,
        "build_results_s": round(statistics.median(t_insert), 3),
        "triangle_mesh_s": round(statistics.median(t_mesh), 3),
        "from_pydata_s": round(t_pydata[0], 3),
        "all_build_results_s": [round(t, 3) for t in t_insert],
    }
    print(f"insert: {results['insert_mesh']}", flush=True)
    results["load_avg_end"] = round(os.getloadavg()[0], 2)
    shutil.rmtree(work, ignore_errors=True)

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(results, indent=2) + "\n")
    imp_p, imp_n, ins = results["import_ply"], results["import_npz"], results["insert_mesh"]
    md = [
        "# Blender add-on I/O (bpy module)",
        "",
        f"bpy {results['bpy']}, Python {results['python']}, {results['cpus']} CPUs shared with other jobs "
        f"(1-min load average {results['load_avg_start']} at start, {results['load_avg_end']} at end), median of "
        f"{args.repeat}. Produced by `benchmarks/blender_io.py`.",
        "",
        "| operation | size | total (s) | of which core `hgca read` (s) | Blender build (s) |",
        "| --- | --- | --- | --- | --- |",
        f"| import binary PLY ({imp_p['file_mb']} MB) | {imp_p['points']:,} points | {imp_p['total_s']} | "
        f"{imp_p['core_read_s']} | {imp_p['blender_build_s']} |",
        f"| import NPZ ({imp_n['file_mb']} MB) | {imp_n['points']:,} points | {imp_n['total_s']} | "
        f"{imp_n['core_read_s']} | {imp_n['blender_build_s']} |",
        "",
        "| mesh insertion | vertices | triangles | time (s) |",
        "| --- | --- | --- | --- |",
        f"| `build_results` (npz load + checks + mesh with edges + attribute + material + collection) | "
        f"{ins['vertices']:,} | {ins['triangles']:,} | {ins['build_results_s']} |",
        f"| `triangle_mesh` (foreach_set + calc_edges) | {ins['vertices']:,} | {ins['triangles']:,} | "
        f"{ins['triangle_mesh_s']} |",
        f"| `from_pydata` + calc_edges (reference, 1 run) | {ins['vertices']:,} | {ins['triangles']:,} | "
        f"{ins['from_pydata_s']} |",
        "",
    ]
    out.with_suffix(".md").write_text("\n".join(md))
    print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

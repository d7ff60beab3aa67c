"""Cycles renders of real completions through the batch path, coloured by observed/generated and by agreement.

    .venv/bin/python benchmarks/blender_render.py [--size 480x320] [--render-samples 16] [--samples 2]

For the nuScenes sweep and two sweeps of the Argoverse 2 log in tests/data/real, each at the default region
(`hgca region`: 38.4 x 38.4 x 8 m around the sensor), full stage:

1. `python -m hgca_blender.batch SCAN --samples K --simplify modifier --max-faces 1000000 --render ...` completes,
   saves the .blend (every triangle kept, a Decimate modifier showing 1 M) and renders it with Cycles (CPU),
   coloured grey where observed and orange where generated;
2. the saved .blend is opened again, coloured by agreement across the K samples, and rendered from the same camera;
3. with the Decimate modifiers applied, the .blend is saved again: its size is that of 1 M-triangle samples.

Writes benchmarks/results/blender_render.{md,json,png} and blender_render_<scan>_<colouring>.png beside them.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
REAL = REPO / "tests" / "data" / "real"
CASES = {
    "nuscenes": ([REAL / "nuscenes_lidar_top_1532402927647951.pcd.bin"], []),
    "av2": ([REAL / "av2" / "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"], ["--frames", "0:2"]),
}
MAX_FACES = 1_000_000


def run_batch(name: str, scans: list[Path], extra: list[str], blend: Path, png: Path, args: argparse.Namespace
              ) -> dict:
    cmd = [sys.executable, "-m", "hgca_blender.batch", *map(str, scans), *extra, "--samples", str(args.samples),
           "--stage", args.stage, "--simplify", "modifier", "--max-faces", str(MAX_FACES), "--python", args.python,
           "--out", str(blend), "--render", str(png), "--render-size", args.size,
           "--render-samples", str(args.render_samples)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=3600,
                          env={**os.environ, "BLENDER_USER_RESOURCES": tempfile.mkdtemp(prefix="hgca_bl_")})
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{name}: batch failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    out = proc.stdout
    imported = re.search(r"imported ([\d,]+) points .* in ([\d.]+) s", out)
    done = re.search(r"Done: .* after ([\d.]+) s", out)
    triangles = [int(t.replace(",", "")) for t in re.findall(r"sample \d+: ([\d,]+) triangles", out)]
    saved = re.search(r"saved .*: ([\d.]+) MiB, ([\d.]+) MiB a sample", out)
    rendered = re.search(r"rendered (.*)", out)
    if not (imported and done and triangles and saved and rendered):
        raise RuntimeError(f"{name}: unexpected batch output:\n{out[-3000:]}")
    return {"points": int(imported.group(1).replace(",", "")), "import_s": float(imported.group(2)),
            "completed_after_s": float(done.group(1)), "batch_wall_s": round(wall, 1), "triangles": triangles,
            "blend_mib": float(saved.group(1)), "blend_mib_per_sample": float(saved.group(2)), "log": out}


def blend_facts(blend: Path) -> dict:
    """What a saved batch .blend holds (for --from-blend): scan points, triangles a sample, MiB a sample."""
    import bpy

    from hgca_blender.scene import mesh_build

    bpy.ops.wm.open_mainfile(filepath=str(blend))
    scans = [o for o in bpy.data.objects if o.get(mesh_build.ROLE_KEY) == "scan"]
    results = sorted((o for o in bpy.data.objects if o.get(mesh_build.ROLE_KEY) == "result"),
                     key=lambda o: int(o["hgca_sample"]))
    size = blend.stat().st_size / 2**20
    return {"points": sum(len(o.data.vertices) for o in scans), "triangles": [len(o.data.polygons) for o in results],
            "blend_mib": round(size, 1), "blend_mib_per_sample": round(size / len(results), 1),
            "import_s": None, "completed_after_s": None, "batch_wall_s": None}


def agreement_and_baked(blend: Path, png: Path, baked: Path) -> dict:
    """Render the saved .blend coloured by agreement; then apply the Decimate modifiers and save a copy."""
    import bpy

    from hgca_blender.scene import mesh_build, preview

    if png.is_file() and baked.is_file():  # --from-blend: both made already, measure the baked copy
        facts = blend_facts(baked)
        return {"agreement_render_s": None, "baked_triangles": facts["triangles"],
                "baked_blend_mib": facts["blend_mib"], "baked_blend_mib_per_sample": facts["blend_mib_per_sample"]}
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    scene = bpy.context.scene
    results = sorted((o for o in bpy.data.objects if o.get(mesh_build.ROLE_KEY) == "result"),
                     key=lambda o: int(o["hgca_sample"]))
    if not mesh_build.color_results_by(results, mesh_build.AGREEMENT_COLOR):
        raise RuntimeError("no agreement colours: the completion needs 2 or more samples")
    render_s = None
    if not png.is_file():  # --from-blend keeps a render made already
        t0 = time.perf_counter()
        preview.render_png(scene, png)
        render_s = round(time.perf_counter() - t0, 1)
    for obj in results:
        mod = obj.modifiers.get(mesh_build.DECIMATE_MODIFIER)
        if mod is not None:
            with bpy.context.temp_override(object=obj, active_object=obj, selected_objects=[obj]):
                bpy.ops.object.modifier_apply(modifier=mod.name)
    faces = [len(o.data.polygons) for o in results]
    bpy.ops.wm.save_as_mainfile(filepath=str(baked), check_existing=False, copy=True)
    size = baked.stat().st_size / 2**20
    return {"agreement_render_s": render_s, "baked_triangles": faces,
            "baked_blend_mib": round(size, 1), "baked_blend_mib_per_sample": round(size / len(results), 1)}


def contact_sheet(rows: list[tuple[str, Path, Path]], path: Path) -> None:
    from PIL import Image, ImageDraw

    images = [[Image.open(a).convert("RGB"), Image.open(b).convert("RGB")] for _, a, b in rows]
    w, h = images[0][0].size
    sheet = Image.new("RGB", (2 * w, len(rows) * (h + 20)), "white")
    draw = ImageDraw.Draw(sheet)
    for r, ((name, _, _), pair) in enumerate(zip(rows, images)):
        for c, (image, label) in enumerate(zip(pair, ("observed (grey) / generated (orange)", "agreement of samples"))):
            sheet.paste(image, (c * w, r * (h + 20) + 20))
            draw.text((c * w + 6, r * (h + 20) + 4), f"{name}: {label}", fill="black")
    sheet.save(path)


def write_page(results: dict, args: argparse.Namespace, out_dir: Path) -> None:
    lines = [
        "# Blender renders of real completions",
        "",
        "Cycles (CPU) renders through the batch path (`python -m hgca_blender.batch`), default region "
        f"(38.4 x 38.4 x 8 m around the sensor), {args.stage} stage, {args.samples} samples, {args.size} px, "
        f"{args.render_samples} render samples. Measured by `benchmarks/blender_render.py` on "
        f"{platform.machine()}, {os.cpu_count()} cores, shared with other jobs (times are upper bounds).",
        "",
        "![renders](blender_render.png)",
        "",
        "Left: grey where the scan saw the surface, orange where hgca generated it. Right: how many of the samples "
        "put a surface there (yellow: all of them; teal to purple: fewer): the model's own confidence.",
        "",
        "| scan | points | triangles per sample (all kept) | .blend MiB per sample, all kept | "
        "MiB per sample at 1 M triangles (Decimate applied) | import (s) | completed after (s) | batch wall (s) | agreement render (s) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    def cell(v) -> str:
        return "-" if v is None else str(v)

    for name, r in results.items():
        r = {k: cell(v) if k.endswith("_s") else v for k, v in r.items()}
        lines.append(f"| {name} | {r['points']:,} | {', '.join(f'{t:,}' for t in r['triangles'])} | "
                     f"{r['blend_mib_per_sample']} | {r['baked_blend_mib_per_sample']} | {r['import_s']} | "
                     f"{r['completed_after_s']} | {r['batch_wall_s']} | {r['agreement_render_s']} |")
    lines += ["", "A '-': not timed in this run (its .blend measured again with `--from-blend`).",
              "", "Each row's renders: " + ", ".join(f"[{n} observed](blender_render_{n}_observed.png), "
                                                    f"[{n} agreement](blender_render_{n}_agreement.png)" for n in results), ""]
    (out_dir / "blender_render.md").write_text("\n".join(lines))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--size", default="480x320")
    p.add_argument("--render-samples", type=int, default=16)
    p.add_argument("--samples", type=int, default=2, help="completions per scan (agreement needs 2 or more)")
    p.add_argument("--stage", choices=("coarse", "full"), default="full")
    p.add_argument("--python", default=sys.executable, help="the core's interpreter")
    p.add_argument("--cases", default=",".join(CASES))
    p.add_argument("--out-dir", type=Path, default=REPO / "benchmarks" / "results")
    p.add_argument("--from-blend", type=Path, default=None, metavar="DIR",
                   help="measure NAME.blend files a run saved in DIR instead of running the batch again")
    args = p.parse_args()
    out_dir = args.out_dir
    out_dir.mkdir(parents=True, exist_ok=True)
    work = args.from_blend or Path(tempfile.mkdtemp(prefix="hgca_render_"))
    results, rows = {}, []
    for name in args.cases.split(","):
        scans, extra = CASES[name]
        blend, observed, agreement = work / f"{name}.blend", out_dir / f"blender_render_{name}_observed.png", \
            out_dir / f"blender_render_{name}_agreement.png"
        r = blend_facts(blend) if args.from_blend else run_batch(name, scans, extra, blend, observed, args)
        r.update(agreement_and_baked(blend, agreement, work / f"{name}_baked.blend"))
        print(f"{name}: {r['triangles']} triangles, {r['blend_mib_per_sample']} MiB a sample "
              f"({r['baked_blend_mib_per_sample']} at 1 M), batch {r['batch_wall_s']} s", flush=True)
        results[name] = {k: v for k, v in r.items() if k != "log"}
        rows.append((name, observed, agreement))
        (out_dir / "blender_render.json").write_text(json.dumps({"results": results}, indent=2))  # kept if stopped
    contact_sheet(rows, out_dir / "blender_render.png")
    meta = {"machine": platform.machine(), "cores": os.cpu_count(), "size": args.size,
            "render_samples": args.render_samples, "samples": args.samples, "load_avg": os.getloadavg()}
    (out_dir / "blender_render.json").write_text(json.dumps({"meta": meta, "results": results}, indent=2))
    write_page(results, args, out_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Mesh-quality benchmark of the fine stage (run by hand): `python benchmarks/mesh_quality.py [options]`.

Before = the earlier mesher (marching cubes of {d < 3 cm}, a two-sheet shell; tests/meshing_reference.py), after =
the single-layer surface of `hgca_core.meshing.fine.udf_mesh`, both from the same fine-stage cells and latents. Per
synthetic test scene (and the real nuScenes / Argoverse 2 fixtures): layers per vertical ray on flat road and
sidewalk patches, RMS height residual to a plane per 2 x 2 m patch (mesh, input points, ground truth), triangles,
non-manifold edges, boundary length, connected pieces, meshing time, and the decimated mesh's Chamfer distance
to the undecimated one; over the synthetic scenes the implicit row's ReSim / IoU / Street CD before and after.
Writes benchmarks/results/mesh_quality.{md,json} and mesh_quality.png (close-ups before / after).
"""
from __future__ import annotations

import argparse
import gc
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from common import REPO
from hgca_core.geometry.region import Region
from hgca_core.meshing import mesh_clean as mc
from hgca_core.meshing.decimation import DEFAULT_MAX_FACES, decimate
from hgca_core.meshing.field import udf_grid
from hgca_core.meshing.fine import udf_mesh
from hgca_core.metrics import flatness
from hgca_core.metrics.surface import mesh_chamfer
from hgca_core.pipeline import Models, complete_local, load_models
from meshing_reference import shell_mesh

OUT = REPO / "benchmarks" / "results" / "mesh_quality"


def fine_state(models: Models, points: np.ndarray, region: Region, seed: int, cache: Path | None, name: str,
               origins: np.ndarray | None = None, origin_index: np.ndarray | None = None
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """(10 cm cells, latents) of one completion as `hgca complete` / `hgca eval` make it (the product's
    `pipeline.complete_local` with the full-stage `models`, free space from the sensor origins, seed `seed`),
    cached by name. points, origins: region frame."""
    path = cache / f"{name}_s{seed}.npz" if cache else None
    if path is not None and path.exists():
        z = np.load(path)
        return torch.from_numpy(z["cells10"]), torch.from_numpy(z["latents"])
    done = complete_local(points, region, models, stage="full", samples=1, seed=seed, max_faces=0, origins=origins,
                          origin_index=origin_index)[0]
    cells10, z = done.fine_cells, done.fine_latents
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, cells10=cells10, latents=z)
    return torch.from_numpy(cells10), torch.from_numpy(z)


def mesh_stats(mesh: trimesh.Trimesh) -> dict:
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    e = mc.edge_stats(f, len(v))
    pieces, label = mc.components(f, len(v))
    return {"triangles": len(f), "nonmanifold_edges": e["nonmanifold"], "boundary_m": mc.boundary_length(v, f),
            "pieces": pieces, "pieces_small": int((np.bincount(label) < 100).sum()) if len(f) else 0}


def load_uptime() -> float:
    return float(os.getloadavg()[0])


def mesh_both(ae, cells10, z, points, sensors) -> dict:
    """Before (shell) / one surface not faired / after (faired, the product's) / light (decimated) meshes of
    one fine-stage result, with the after path's timings."""
    t = time.perf_counter()
    g, vals = udf_grid(ae, cells10, z)
    t_decode = time.perf_counter() - t
    before = shell_mesh(g, vals)
    unfaired = udf_mesh(ae, cells10, z, voxel=ae.cfg.voxel, points=points, sensors=sensors, fair=False)
    timings: dict = {}
    t = time.perf_counter()
    after = udf_mesh(ae, cells10, z, voxel=ae.cfg.voxel, points=points, sensors=sensors, timings=timings)
    t_mesh = time.perf_counter() - t
    t = time.perf_counter()
    light = decimate(after, DEFAULT_MAX_FACES)
    timings["decimate"] = time.perf_counter() - t
    timings["meshing"] = t_mesh
    timings["decode_alone"] = t_decode
    timings["load"] = load_uptime()
    return {"before": before, "unfaired": unfaired, "after": after, "light": light, "timings": timings}


MESHES = ("before", "unfaired", "after", "light")


def ground(meshes: dict, patches: flatness.Patches, ref: dict, truth: np.ndarray | None = None) -> dict:
    return {k: flatness.ground_report(meshes[k], patches, ref if k == "after" else None, truth=truth)
            for k in MESHES}


def synthetic_scene(path: Path, samples: int, cache: Path | None, models: Models) -> tuple[dict, dict, dict]:
    from hgca_core.dataset.samples import load_sample

    s = load_sample(path)
    region = Region.parse(",".join(str(v) for v in np.asarray(s["region"])))
    pts = np.asarray(s["input_points"], dtype=np.float64)
    sensors = np.asarray(s["input_origins"], dtype=np.float64)
    patches = flatness.flat_patches_from_labels(s["gt_surface"], s["gt_surface_label"])
    ref = {"input": pts, "gt": np.asarray(s["gt_surface"])}
    row: dict = {}
    first = None
    done: dict[str, list] = {"before": [], "unfaired": [], "after": []}
    for i in range(samples):
        cells10, z = fine_state(models, pts, region, i, cache, path.stem, sensors,
                                np.asarray(s["input_scan_index"]))
        m = mesh_both(models.autoencoder, cells10, z, pts, sensors)
        for k in done:   # bare copies, without the ray tests' BVHs
            done[k].append(trimesh.Trimesh(m[k].vertices, m[k].faces, process=False))
        if i == 0:
            first = m
            row = {"scene": path.stem, "timings": m["timings"], "ground": ground(m, patches, ref, ref["gt"]),
                   "stats": {k: mesh_stats(m[k]) for k in MESHES},
                   "chamfer_light_m": mesh_chamfer(m["light"], m["after"])}
        else:
            del m
            gc.collect()
    return row, done, {"sample": s, "first": first}


def real_scene(name: str, points: np.ndarray, origins: np.ndarray, index: np.ndarray, cache: Path | None,
               models: Models) -> dict:
    """One real input (world frame, each point's origin row in `index`) in its default region, as eval-real."""
    region = Region.around(points, sensor=origins[0])
    local = region.to_local(points)
    sensors = region.to_local(origins)
    cells10, z = fine_state(models, local, region, 0, cache, name, sensors, index)
    inside = local[region.contains_local(local)]
    m = mesh_both(models.autoencoder, cells10, z, inside, sensors)
    patches = flatness.flat_patches_from_points(inside, max_rms=0.03)
    anyp = flatness.flat_patches_from_points(inside, max_rms=0.03, max_above=1.0)   # objects allowed
    return {"scene": name, "timings": m["timings"], "ground": ground(m, patches, {"input": inside}),
            "ground_with_objects": flatness.ground_report(m["after"], anyp, {"input": inside}),
            "stats": {k: mesh_stats(m[k]) for k in MESHES},
            "chamfer_light_m": mesh_chamfer(m["light"], m["after"])}


def real_inputs(root: Path) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(points, origins, each point's origin row) of the real fixtures `hgca eval-real` scores by default (both
    Argoverse 2 logs and the nuScenes sweep, those present under `root`), world frame."""
    from hgca_core.commands.eval_real import inputs_of
    from hgca_core.metrics.real_eval import input_rays

    items = inputs_of(argparse.Namespace(inputs=[], real_dir=str(root)))
    return {item["name"]: input_rays(item) for item in items if Path(item["path"]).exists()}


def closeups(scene: dict, path: Path) -> None:
    """Before / after ray-cast close-ups of a flat road patch, the facade and the parked car nearest the ego
    sensor of one synthetic scene."""
    from PIL import Image, ImageDraw

    from hgca_core.render import render_closeup

    s, m = scene["sample"], scene["first"]
    o = np.asarray(s["input_origins"][0], dtype=np.float64)
    gt, lab = np.asarray(s["gt_surface"], dtype=np.float64), np.asarray(s["gt_surface_label"])
    gz = float(np.asarray(s["ground_z"]))
    patches = flatness.flat_patches_from_labels(gt, lab, ground_labels=(0,))
    c = patches.corners + patches.size / 2
    road = np.r_[c[np.argmin(np.linalg.norm(c - o[:2], axis=1))], gz]
    views = [("road", road + [-2.5, -2.5, 1.6], road)]
    for name, label in (("facade", 2), ("parked car", 3)):
        p = gt[lab == label]
        if len(p) == 0:
            continue
        near = p[np.argmin(np.linalg.norm(p[:, :2] - o[:2], axis=1))]
        centre = p[np.linalg.norm(p[:, :2] - near[:2], axis=1) < (3.0 if label == 3 else 4.0)].mean(0)
        away = o[:2] - centre[:2]
        away /= max(np.linalg.norm(away), 1e-9)
        dist = 5.0 if label == 3 else 6.0
        eye = np.r_[centre[:2] + away * dist + np.array([-away[1], away[0]]) * 2.0, gz + 2.2]
        views.append((name, eye, np.r_[centre[:2], gz + (0.8 if label == 3 else 2.0)]))
    tiles = []
    for name, eye, target in views:
        row = [render_closeup(m[k], eye, target, size=(480, 320), light=np.array([0.9, 0.25, 0.35]))
               for k in ("before", "unfaired", "light")]
        tiles.append(np.concatenate(row, 1))
    img = Image.fromarray(np.concatenate(tiles, 0))
    draw = ImageDraw.Draw(img)
    for r, (name, _, _) in enumerate(views):
        draw.text((6, 6 + 320 * r), f"{name}: before (3 cm shell)", fill=(200, 0, 0))
        draw.text((486, 6 + 320 * r), f"{name}: one surface, not faired", fill=(160, 90, 0))
        draw.text((966, 6 + 320 * r), f"{name}: after (one surface, faired, <= 1 M triangles)", fill=(0, 120, 0))
    img.save(path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default="data/synth", help="dataset folder with a test split (hgca synth)")
    p.add_argument("--count", type=int, default=4, help="synthetic test scenes")
    p.add_argument("--samples", type=int, default=3, help="completions per scene for the metrics (k)")
    p.add_argument("--real", default=str(REPO.parent / "shared" / "fixtures" / "real"),
                   help="real fixtures folder ('' to skip the real scans)")
    p.add_argument("--cache", default=None, help="folder to keep fine-stage results between runs")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--skip-eval", action="store_true", help="no ReSim / IoU / Street CD")
    p.add_argument("--fine-weights", default=None, help="fine weights to measure (default: the shipped fine.pt)")
    p.add_argument("--out", default=str(OUT))
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    from hgca_core.metrics.evaluate import aggregate, evaluate_sample, format_table
    from hgca_core.dataset.samples import split_files

    cache = Path(args.cache) if args.cache else None
    models = load_models("full", None, args.fine_weights)
    ae = models.autoencoder
    udf_mesh(ae, torch.zeros((1, 3), dtype=torch.long), torch.zeros((1, ae.cfg.latent)))  # warm-up
    result: dict = {"scenes": [], "real": [], "threads": args.threads}
    evals: dict = {"before": [], "unfaired": [], "after": []}
    first_scene = None
    for path in split_files(args.data, "test")[: args.count]:
        row, meshes, scene = synthetic_scene(Path(path), args.samples, cache, models)
        result["scenes"].append(row)
        first_scene = first_scene or scene
        if not args.skip_eval:
            for k in list(meshes):   # one kind at a time, freed after its scores (their ray BVHs are large)
                evals[k].append(evaluate_sample(scene["sample"], meshes.pop(k)))
        del meshes
        gc.collect()   # trimesh's caches hold cycles (mesh <-> ray intersector): without this, > 20 GB by scene 4
        print(json.dumps(row, default=float), flush=True)
    for name, (points, origins, index) in (real_inputs(Path(args.real)) if args.real else {}).items():
        row = real_scene(name, points, origins, index, cache, models)
        result["real"].append(row)
        print(json.dumps(row, default=float), flush=True)
    if not args.skip_eval and evals["after"]:
        result["eval"] = {k: aggregate(v) for k, v in evals.items()}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if first_scene is not None:
        closeups(first_scene, out.with_suffix(".png"))
    out.with_suffix(".json").write_text(json.dumps(result, indent=1, default=float))
    out.with_suffix(".md").write_text(report(result, format_table))
    print(out.with_suffix(".md").read_text())
    return 0


def report(result: dict, format_table) -> str:
    import platform

    lines = [f"Mesh quality of the fine stage: before (marching cubes of d < 3 cm: a two-sheet shell) and after "
             f"(the zero level as one surface, `hgca_core.meshing.fine.udf_mesh`), from the same fine-stage results.",
             f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch "
             f"{torch.__version__} ({result['threads']} threads); load average (1 min) at each timing in the "
             f"last column: other jobs shared the cores, so times are upper bounds.", "",
             "| scene | mesh | one layer (%) | no layer (%) | 2+ layers (%) | ground RMS mesh (mm) | input (mm) | "
             "GT (mm) | mesh to GT plane (mm) | patches | triangles | non-manifold edges | boundary (m) | pieces | "
             "meshing (s) | load |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in result["scenes"] + result["real"]:
        t = row["timings"]
        g_after = row["ground"]["after"]
        for k, label in (("before", "before: shell"), ("unfaired", "one surface, not faired"),
                         ("after", "after: one surface, faired"),
                         ("light", f"after, decimated to {DEFAULT_MAX_FACES:,}")):
            g, st = row["ground"][k], row["stats"][k]
            secs = (f"{t['decode'] + t['extract'] + t['clean'] + t['fair']:.1f} (decode {t['decode']:.1f}, "
                    f"extract {t['extract']:.1f}, clean {t['clean']:.1f}, fair {t['fair']:.1f})" if k == "after" else
                    f"+{t['decimate']:.1f} decimation" if k == "light" else "-")
            lines.append(f"| {row['scene']} | {label} | {100 * g['one_layer']:.1f} | {100 * g['no_layer']:.1f} | "
                         f"{100 * g['two_plus']:.1f} | {1000 * g['rms_mesh']:.1f} | "
                         f"{1000 * g_after.get('rms_input', float('nan')):.1f} | "
                         f"{1000 * g_after.get('rms_gt', float('nan')):.1f} | "
                         f"{1000 * g.get('rms_to_truth', float('nan')):.1f} | {int(g['patches'])} | "
                         f"{st['triangles']:,} | {st['nonmanifold_edges']:,} | {st['boundary_m']:.0f} | "
                         f"{st['pieces']} | {secs} | {t['load']:.1f} |")
    lines += ["", "Chamfer distance of the decimated mesh to the undecimated one (mean of both directions of the "
              "point-to-surface distance of 200,000 samples): " + ", ".join(f"{r['scene']} {1000 * r['chamfer_light_m']:.2f} mm"
                                               for r in result["scenes"] + result["real"])]
    if result["real"]:
        lines += ["", "Real scans with every flat-bottomed patch counted (objects inside allowed, the definition of "
                  "the first run of this benchmark), after: " + "; ".join(
                      f"{r['scene']} {int(r['ground_with_objects']['patches'])} patches, one layer "
                      f"{100 * r['ground_with_objects']['one_layer']:.1f} %, none "
                      f"{100 * r['ground_with_objects']['no_layer']:.1f} %, RMS "
                      f"{1000 * r['ground_with_objects']['rms_mesh']:.1f} mm (input "
                      f"{1000 * r['ground_with_objects']['rms_input']:.1f} mm)"
                      for r in result["real"] if "ground_with_objects" in r)]
    if "eval" in result:
        names = {"before": "before: shell", "unfaired": "one surface, not faired",
                 "after": "after: one surface, faired"}
        rows = {f"hGCA (implicit), {names[k]}": {**v, "representation": "implicit"}
                for k, v in result["eval"].items()}
        lines += ["", f"Implicit row of the paper's Table 1 on these {result['eval']['after']['n']} test scenes, "
                  f"k = {result['eval']['after']['k']} (same fine-stage results meshed both ways; undecimated):", "",
                  format_table(rows)]
    lines += ["", "Ground patches: 2 x 2 m patches of flat road or sidewalk (synthetic: ground-truth labels, no kerb "
              "or object inside; real: patches whose lowest input points fit a plane to 3 cm and with at most 2 % of "
              "their points more than 15 cm above it, i.e. no car or planter inside), vertical rays every "
              "10 cm; a layer is a surface within 15 cm of the patch's ground height; RMS is the mean over "
              "patches of the residual to a plane fitted to the rays' first hits (input points / GT samples within "
              "15 cm for the reference columns).", "", "![before / after close-ups](mesh_quality.png)"]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())

"""Whole-drive benchmark (run by hand): `hgca drive` on a synthetic drive of two street scenes end to end.

    .venv/bin/python benchmarks/drive.py [--stage coarse|full] [--work DIR] [--spacing 8]

Two seeded straight city scenes (`hgca_core.synth.scene`, 120 m each) one after the other make a street of
240 m; the ego vehicle drives ~230 m along it and scans every `--spacing` m (the Waymo profile, the paper's
noise). Then, each as the CLI in its
own process: `hgca drive` on 1 worker (in-process), on 2 local Ray workers, and without neighbour
conditioning (`--no-seams`, phase-one tiles taken from the 1-worker run's cache: they are the same tiles).
Measured: wall time, tiles per minute, peak RSS of the driver and of each worker, and seam quality: IoU of the
merged result's 20 cm cells against the scenes' ground truth in the overlap bands (places two tiles cover)
vs inside tiles (places one tile covers), and how well neighbouring tiles agree in their overlaps.
Results: benchmarks/results/drive.{md,json,png}.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests" / "drive"))

from drive_data import save_scans  # noqa: E402  (the tests' scan writer: npz in the sensor frame + poses.json)

from hgca_core.geometry.keys import pack, unpack  # noqa: E402
from hgca_core.geometry.region import Region  # noqa: E402
from hgca_core.geometry.voxel import COARSE, cell_centers, voxelize  # noqa: E402
from hgca_core.hardware import machine  # noqa: E402
from hgca_core.tiling.plan import footprint_contains, owned  # noqa: E402
from hgca_core.tiling.store import DriveStore  # noqa: E402

SEEDS = (4_000_011, 4_000_010)   # two straight city streets (flat; a 0.9 % grade), both driven towards +x
SCENE = 120.0                    # the layout square of a scene; the second goes 120 m further along x
WRAP = ("import resource, sys; from hgca_core.cli import main; rc = main(sys.argv[1:]); "
        "print('MAXRSS', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr); sys.exit(rc)")


def scenes() -> list[tuple]:
    """(scene, shift): the second scene moved so that its drive starts where the first one's ends (x + 120 m,
    the road heights matched)."""
    from hgca_core.synth.scene import make_scene

    a, b = (make_scene(s, "city") for s in SEEDS)
    shift = np.array([SCENE, *(a.drive[-1, 1:] - b.drive[0, 1:])])
    shift[1] = 0.0
    return [(a, np.zeros(3)), (b, shift)]


def _side(x: np.ndarray, k: int) -> np.ndarray:
    """Which world x belong to scene k of the stitched street (the first up to x = 60 m, the second beyond)."""
    return x < SCENE / 2 if k == 0 else x >= SCENE / 2


def build_drive(folder: Path, spacing: float, seed: int = 0) -> tuple[list[Path], Path, float]:
    """The stitched street scanned by the paper's sensor (WAYMO64 geometry, the paper's noise) every `spacing` m."""
    import trimesh

    from hgca_core.geometry.raycast import make_intersector
    from hgca_core.synth.dataset import Drive
    from hgca_core.synth.lidar import PAPER_EFFECTS, PROFILES, Unit, scan

    meshes, materials, drive, up = [], [], [], []
    for k, (scene, shift) in enumerate(scenes_cached()):
        m = scene.mesh.copy()
        m.apply_translation(shift)
        keep = _side(m.triangles_center[:, 0], k)          # each scene's ground reaches past the join: cut it
        m.update_faces(keep)
        meshes.append(m)
        materials.append(np.asarray(scene.face_materials)[keep])
        drive.append(scene.drive + shift)
        up.append(scene.drive_up)
    inter = make_intersector(trimesh.util.concatenate(meshes))
    path = Drive(np.concatenate(drive), np.concatenate(up))
    rng = np.random.default_rng(seed)
    unit = Unit.draw(PROFILES["waymo"], rng, PAPER_EFFECTS)
    arcs = np.arange(2.0, path.length - 2.0 + 1e-9, spacing)
    scans = [scan(inter, np.concatenate(materials), path.pose(a), unit, rng, PAPER_EFFECTS) for a in arcs]
    paths, poses_path = save_scans(folder, [sc.points for sc in scans], [sc.pose for sc in scans])
    return paths, poses_path, float(arcs[-1] - arcs[0])


def ground_truth(region: Region, density: float = 400.0) -> np.ndarray:
    """20 cm cells (region frame) of the street's surface a complete scan could see (`synth.groundtruth`), each
    scene's on its side of the join."""
    from hgca_core.synth.groundtruth import RegionSurface

    cells = []
    for k, (scene, shift) in enumerate(scenes_cached()):
        moved = Region(region.center - shift, region.size, region.yaw)    # same frame, scene coordinates
        surf = RegionSurface(scene.mesh, scene.face_labels, scene.solids, moved, np.random.default_rng(k), density,
                             terrain=scene.terrain, ground_faces=scene.ground_faces)
        occ = surf.occupancy()[1].astype(np.int64)
        cells.append(occ[_side(region.to_world(cell_centers(occ, COARSE))[:, 0], k)])
    return np.unique(np.concatenate(cells), axis=0)


_SCENES: list = []


def scenes_cached() -> list[tuple]:
    if not _SCENES:
        _SCENES.extend(scenes())
    return _SCENES


def run_cli(args: list, log: Path) -> dict:
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", WRAP, "drive", *map(str, args), "--progress", "none"],
                          capture_output=True, text=True, cwd=REPO)
    wall = time.perf_counter() - t
    log.write_text(proc.stderr)
    if proc.returncode != 0:
        raise SystemExit(f"hgca drive failed ({proc.returncode}): {proc.stderr[-3000:]}")
    rss = [int(line.split()[1]) * 1024 for line in proc.stderr.splitlines() if line.startswith("MAXRSS")]
    return {"wall_s": round(wall, 1), "driver_peak_rss_gib": round(rss[-1] / 2**30, 2)}


def summarise(out: Path, measured: dict) -> dict:
    doc = json.loads((out / "drive.json").read_text())
    workers: dict[str, int] = {}
    for t in doc["tiles"]:
        if t.get("run") == doc["runs"]:
            workers[t["worker"]] = max(workers.get(t["worker"], 0), t["peak_rss"])
    return {**measured, "tiles": len(doc["tiles"]), "computed": doc["timings"]["tiles_computed"],
            "tiles_s": doc["timings"]["tiles_s"], "engine_start_s": doc["timings"].get("engine_start_s", 0.0),
            "merge_s": doc["timings"]["merge_s"], "tiles_per_min": doc["timings"]["tiles_per_min"],
            "tile_s_mean": round(float(np.mean([t["seconds"] for t in doc["tiles"] if t.get("run") == doc["runs"]])), 1),
            "worker_peak_rss_gib": sorted(round(v / 2**30, 2) for v in workers.values())}


def centre_cells(cells: np.ndarray, source: Region, target: Region) -> np.ndarray:
    """Cells of `source` by their centres into `target`'s grid (one cell each; for agreement between tiles)."""
    return voxelize(target.to_local(source.to_world(cell_centers(cells, COARSE))), COARSE, target.size)


def seam_scores(out: Path, gts: list[np.ndarray]) -> dict:
    """IoU against ground truth in the overlap bands and inside tiles (each place scored on the tile that owns
    it in the merged mesh), and the IoU between neighbours' cells in their overlaps."""
    doc = json.loads((out / "drive.json").read_text())
    store = DriveStore(out)
    regions = [Region.from_tuple(t["region"]) for t in doc["tiles"]]
    cells = [store.load(t["key"], only=0)["samples"][0]["cells"].astype(np.int64) for t in doc["tiles"]]
    counts = {"band": [0, 0], "interior": [0, 0]}

    def where(c: np.ndarray, i: int) -> tuple[np.ndarray, np.ndarray]:
        xy = regions[i].to_world(cell_centers(c, COARSE))[:, :2]
        mine = owned(xy, i, regions)
        cover = sum(footprint_contains(r, xy).astype(int) for r in regions)
        return mine & (cover >= 2), mine & (cover == 1)

    for i, (pred, gt) in enumerate(zip(cells, gts)):
        kp, kg = pack(pred), pack(gt)
        both = np.union1d(kp, kg)
        hit = np.isin(both, kp) & np.isin(both, kg)
        band, inner = where(unpack(both, batched=False), i)
        for name, m in (("band", band), ("interior", inner)):
            counts[name][0] += int((hit & m).sum())
            counts[name][1] += int(m.sum())
    agree = []
    for i in range(len(regions) - 1):
        a, b = cells[i], centre_cells(cells[i + 1], regions[i + 1], regions[i])
        ka = pack(a[footprint_contains(regions[i + 1], regions[i].to_world(cell_centers(a, COARSE))[:, :2])])
        kb = pack(b[footprint_contains(regions[i + 1], regions[i].to_world(cell_centers(b, COARSE))[:, :2])])
        agree.append(np.intersect1d(ka, kb).size / max(1, np.union1d(ka, kb).size))
    band, inner = (counts[k][0] / max(1, counts[k][1]) for k in ("band", "interior"))
    return {"iou_band": round(band, 4), "iou_interior": round(inner, 4), "ratio": round(band / inner, 3),
            "neighbour_agreement": round(float(np.mean(agree)), 4), "agreement_per_overlap": [round(a, 3) for a in agree]}


def plot(out: Path, path: Path, scores: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    doc = json.loads((out / "drive.json").read_text())
    store = DriveStore(out)
    regions = [Region.from_tuple(t["region"]) for t in doc["tiles"]]
    fig, ax = plt.subplots(2, 1, figsize=(14, 6.0), gridspec_kw={"height_ratios": [1.4, 1]})
    cmap = plt.get_cmap("tab10")
    for i, (t, r) in enumerate(zip(doc["tiles"], regions)):
        c = store.load(t["key"], only=0)["samples"][0]["cells"].astype(np.int64)
        w = r.to_world(cell_centers(c, COARSE))
        w = w[owned(w[:, :2], i, regions) & (w[:, 2] > r.center[2] - r.size[2] / 2 + 1.3)]   # above the road
        ax[0].scatter(w[:, 0], w[:, 1], s=0.05, color=cmap(i % 10), rasterized=True)
        corners = r.to_world(np.array([[0, 0, 0], [r.size[0], 0, 0], [r.size[0], r.size[1], 0], [0, r.size[1], 0],
                                       [0, 0, 0]], float))
        ax[0].plot(corners[:, 0], corners[:, 1], color=cmap(i % 10), lw=0.8)
    pos = np.array([s["position"] for s in doc["scans"]])
    ax[0].plot(pos[:, 0], pos[:, 1], "k.", ms=3, label="scan positions")
    ax[0].set_aspect("equal")
    ax[0].set_title(f"merged drive, sample 0, cells above the road coloured by owning tile ({len(regions)} tiles, "
                    "boxes = tile footprints)")
    ax[0].legend(loc="upper right")
    names = ["with neighbour conditioning", "without"]
    vals = [scores["seams"], scores["no_seams"]]
    x = np.arange(2)
    ax[1].bar(x - 0.2, [v["iou_interior"] for v in vals], 0.2, label="IoU inside tiles")
    ax[1].bar(x, [v["iou_band"] for v in vals], 0.2, label="IoU in overlap bands")
    ax[1].bar(x + 0.2, [v["neighbour_agreement"] for v in vals], 0.2, label="neighbours agree (IoU)")
    ax[1].set_xticks(x, names)
    ax[1].legend(loc="lower right", fontsize=8)
    ax[1].set_ylim(0, 1)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stage", choices=("coarse", "full"), default="coarse")
    ap.add_argument("--spacing", type=float, default=8.0)
    ap.add_argument("--work", type=Path, default=Path("/tmp/hgca_drive_bench"))
    ap.add_argument("--results", type=Path, default=REPO / "benchmarks" / "results")
    ap.add_argument("--t1", type=int, default=None)
    ap.add_argument("--threads", type=int, default=1,
                    help="torch threads per tile in every run (1: a shared machine's cores are busy; more threads "
                         "than free cores wait for each other)")
    args = ap.parse_args()
    if args.work.exists():
        shutil.rmtree(args.work)
    t = time.perf_counter()
    scans, poses, length = build_drive(args.work / "scans", args.spacing)
    print(f"{len(scans)} scans along {length:.0f} m in {time.perf_counter() - t:.0f} s", flush=True)
    common = [*scans, "--poses", poses, "--stage", args.stage, "--threads", args.threads] + (
        ["--t1", args.t1] if args.t1 else [])
    runs = {}
    runs["1 worker (in-process)"] = summarise(args.work / "w1", run_cli(
        [*common, "--out", args.work / "w1", "--workers", 1], args.work / "w1.log"))
    print(runs, flush=True)
    runs["2 workers (local Ray)"] = summarise(args.work / "w2", run_cli(
        [*common, "--out", args.work / "w2", "--workers", 2], args.work / "w2.log"))
    print(runs, flush=True)
    same = all((args.work / "w1" / f).read_bytes() == (args.work / "w2" / f).read_bytes() for f in ["drive_s0.ply"])
    shutil.copytree(args.work / "w1" / "cache", args.work / "noseams" / "cache")   # phase one is the same tiles
    run_cli([*common, "--out", args.work / "noseams", "--no-seams"], args.work / "noseams.log")
    doc = json.loads((args.work / "w1" / "drive.json").read_text())
    gts = [ground_truth(Region.from_tuple(t["region"])) for t in doc["tiles"]]
    scores = {"seams": seam_scores(args.work / "w1", gts), "no_seams": seam_scores(args.work / "noseams", gts)}
    result = {"machine": machine(), "load_average": [round(v, 1) for v in os.getloadavg()],
              "threads_per_tile": args.threads, "stage": args.stage, "t1": args.t1, "length_m": round(length, 1),
              "scans": len(scans), "spacing_m": args.spacing, "plan": doc["plan"], "runs": runs,
              "ray_equals_in_process": same, "seams": scores}
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "drive.json").write_text(json.dumps(result, indent=1))
    (args.results / "drive.md").write_text(table(result))
    plot(args.work / "w1", args.results / "drive.png", scores)
    print(table(result))
    return 0


def table(r: dict) -> str:
    m = r["machine"]
    lines = [f"# Whole-drive benchmark: `hgca drive`, stage {r['stage']}, T1 = {r['t1'] or 'default'}", "",
             f"Machine: {m['cpu']}, {m['cores']} cores shared with other jobs (load average {r['load_average']} "
             f"at the end), torch {m['torch']}, {r['threads_per_tile']} torch thread(s) per tile, {m['date']}. "
             "A synthetic drive of "
             f"{r['length_m']} m (two seeded city scenes, {r['scans']} Waymo-profile scans every {r['spacing_m']} m), "
             f"{r['plan']['size'][0]} m tiles overlapping {r['plan']['overlap']} m, {r['plan']['scans_per_tile']} "
             "scans per tile.", "",
             "| run | tiles | wall (s) | Ray start (s) | tiles (s) | merge (s) | tiles/min | mean tile (s) | "
             "driver peak RSS (GiB) | worker peak RSS (GiB) |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for name, v in r["runs"].items():
        lines.append(f"| {name} | {v['tiles']} | {v['wall_s']} | {v['engine_start_s']} | {v['tiles_s']} | "
                     f"{v['merge_s']} | {v['tiles_per_min']} | {v['tile_s_mean']} | {v['driver_peak_rss_gib']} | "
                     f"{', '.join(map(str, v['worker_peak_rss_gib']))} |")
    lines += ["", f"Ray's merged mesh is byte-identical to the in-process one: {r['ray_equals_in_process']}.", "",
              "| 20 cm cells vs ground truth | IoU inside tiles | IoU in overlap bands | bands / inside | "
              "neighbours agree in overlaps (IoU) |", "|---|---:|---:|---:|---:|"]
    for name, key in (("with neighbour conditioning", "seams"), ("without (--no-seams)", "no_seams")):
        s = r["seams"][key]
        lines.append(f"| {name} | {s['iou_interior']} | {s['iou_band']} | {s['ratio']} | {s['neighbour_agreement']} |")
    lines += ["", "Overlap bands: places two tiles cover, scored on the tile that owns them in the merged mesh; "
              "inside: places one tile covers. Ground truth: the scenes' surface a complete scan could see "
              "(`synth.groundtruth.RegionSurface`), no visibility mask. Neighbour agreement: IoU of two consecutive "
              "tiles' cells in their overlap (the second's mapped by cell centre into the first's grid).",
              "", "![drive](drive.png)", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())

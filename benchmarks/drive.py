"""Whole-drive benchmark (run by hand): `hgca drive` on a 250 m and a 1 km synthetic drive, end to end.

    .venv/bin/python benchmarks/drive.py [--stage coarse|full] [--length 1000] [--short 250] [--until HH:MM]

Seeded straight city scenes (`hgca_core.synth.scene`, 120 m each, two layouts taken in turn) one after the other
make a street; the ego vehicle drives along it and scans every `--spacing` m (the Waymo profile, the paper's
noise). Then, each as the CLI in its own process: `hgca drive` on the short and on the long drive, on 1 worker
(in-process) and on 2 local Ray workers. Measured: wall time, tiles per minute, peak RSS of the driver and of each
worker (flat in the drive's length: a worker holds one tile), and seams on the long drive: IoU of the merged
result's 20 cm cells against the scenes' ground truth in the overlap bands (places two tiles cover) vs inside
tiles, how well neighbouring tiles agree in their overlaps, and every 4 m slab along the drive (recall and IoU
against the ground truth), the worst against the median away from the drive's two ends. `--until` skips a run
that would end after that UTC time (estimated from the tiles measured so far). Results:
benchmarks/results/drive.{md,json,png}.
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from hgca_core.geometry.region import Region
from hgca_core.geometry.voxel import COARSE, cell_centers
from hgca_core.hardware import machine

sys.path.insert(0, str(Path(__file__).resolve().parent))
from drive_scores import ENDS, SCENE, SLAB, plot, seam_scores, slab_sources, worker_growth  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SEEDS = (4_000_011, 4_000_010)   # two straight city streets (flat; a 0.9 % grade), both driven towards +x
TILE_M = 38.4
WRAP = ("import sys; from hgca_core.cli import main; from hgca_core.hardware import peak_rss_bytes; "
        "rc = main(sys.argv[1:]); print('MAXRSS', peak_rss_bytes(), file=sys.stderr); sys.exit(rc)")


def scenes(count: int) -> list[tuple]:
    """(scene, shift) for `count` scenes in a row, the layouts taken in turn, each moved so that its drive starts
    where the previous one's ends (x + 120 m, the road heights matched)."""
    from hgca_core.synth.scene import make_scene

    layouts = [make_scene(s, "city") for s in SEEDS]
    out, z = [], 0.0
    for k in range(count):
        scene = layouts[k % 2]
        if k:
            prev, shift_prev = out[-1]
            z = prev.drive[-1, 2] + shift_prev[2] - scene.drive[0, 2]
        out.append((scene, np.array([k * SCENE, 0.0, z])))
    return out


def _side(x: np.ndarray, k: int, count: int) -> np.ndarray:
    """Which world x belong to scene k of the stitched street (each its 120 m, the two ends open)."""
    lo = -np.inf if k == 0 else (k - 0.5) * SCENE
    hi = np.inf if k == count - 1 else (k + 0.5) * SCENE
    return (x >= lo) & (x < hi)


def save_scans(folder: Path, scans_world: list[np.ndarray], poses: list[np.ndarray]) -> tuple[list[Path], Path]:
    """Each scan (world points, float64) in its sensor frame as scan_<i>.npz, and poses.json (sensor->world)."""
    folder.mkdir(parents=True, exist_ok=True)
    paths, entries = [], []
    for i, (pts, pose) in enumerate(zip(scans_world, poses)):
        path = folder / f"scan_{i:04d}.npz"
        np.savez(path, points=(np.asarray(pts, dtype=np.float64) - pose[:3, 3]) @ pose[:3, :3])
        paths.append(path)
        entries.append({"file": path.name, "pose": np.asarray(pose, dtype=np.float64).tolist()})
    poses_path = folder / "poses.json"
    poses_path.write_text(json.dumps({"scans": entries}))
    return paths, poses_path


def build_drive(folder: Path, length: float, spacing: float, seed: int = 0) -> tuple[list[Path], Path, float, list]:
    """The stitched street scanned by the paper's sensor (WAYMO64 geometry, the paper's noise) every `spacing` m
    over `length` m; each scan sees the scenes around it."""
    import trimesh

    from hgca_core.geometry.raycast import make_intersector
    from hgca_core.synth.dataset import Drive
    from hgca_core.synth.lidar import PAPER_EFFECTS, PROFILES, Unit, scan

    count = int(np.ceil((length + 4.0 - 116.0) / SCENE)) + 1
    placed = scenes(count)
    pieces, drive, up = [], [], []
    for k, (sc, shift) in enumerate(placed):
        m = sc.mesh.copy()
        m.apply_translation(shift)
        keep = _side(m.triangles_center[:, 0], k, count)      # each scene's ground reaches past the join: cut it
        m.update_faces(keep)
        pieces.append((m, np.asarray(sc.face_materials)[keep]))
        drive.append(sc.drive + shift)
        up.append(sc.drive_up)
    path = Drive(np.concatenate(drive), np.concatenate(up))
    rng = np.random.default_rng(seed)
    unit = Unit.draw(PROFILES["waymo"], rng, PAPER_EFFECTS)
    start = 2.0
    arcs = np.arange(start, min(path.length - 2.0, start + length) + 1e-9, spacing)
    inters: dict[int, tuple] = {}
    scans = []
    for a in arcs:
        pose = path.pose(a)
        k = int(np.clip(np.round(pose[0, 3] / SCENE), 0, count - 1))
        if k not in inters:              # the scene the car is in and its two neighbours (a scan reaches ~80 m)
            near = [pieces[j] for j in range(max(0, k - 1), min(count, k + 2))]
            inters = {k: (make_intersector(trimesh.util.concatenate([m for m, _ in near])),
                          np.concatenate([f for _, f in near]))}
        inter, mats = inters[k]
        scans.append(scan(inter, mats, pose, unit, rng, PAPER_EFFECTS))
    paths, poses_path = save_scans(folder, [sc.points for sc in scans], [sc.pose for sc in scans])
    return paths, poses_path, float(arcs[-1] - arcs[0]), placed


def ground_truth(region: Region, placed: list, density: float = 400.0, cache: Path | None = None) -> np.ndarray:
    """20 cm cells (region frame) of the street's surface a complete scan could see (`synth.groundtruth`), each
    scene's on its side of its joins; only the scenes the region reaches. `cache`: a folder keeping them by
    region (they take a while; a tile's region does not change between runs)."""
    import hashlib

    from hgca_core.synth.groundtruth import RegionSurface

    key = hashlib.sha256(np.round(np.array(region.as_tuple(), dtype=np.float64), 6).tobytes()).hexdigest()[:20]
    if cache is not None and (cache / f"{key}.npy").is_file():
        return np.load(cache / f"{key}.npy")

    cells = []
    reach = float(np.hypot(*region.size[:2])) / 2 + SCENE / 2
    for k, (scene, shift) in enumerate(placed):
        if abs(region.center[0] - shift[0]) > reach:
            continue
        moved = Region(region.center - shift, region.size, region.yaw)    # same frame, scene coordinates
        surf = RegionSurface(scene.mesh, scene.face_labels, scene.solids, moved, np.random.default_rng(k), density,
                             terrain=scene.terrain, ground_faces=scene.ground_faces)
        occ = surf.occupancy()[1].astype(np.int64)
        cells.append(occ[_side(region.to_world(cell_centers(occ, COARSE))[:, 0], k, len(placed))])
    out = np.unique(np.concatenate(cells), axis=0)
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)
        np.save(cache / f"{key}.npy", out)
    return out


def run_cli(args: list, log: Path) -> dict:
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", WRAP, "drive", *map(str, args), "--progress", "none"],
                          capture_output=True, text=True, cwd=log.parent)   # not the checkout: -c puts the cwd first
    wall = time.perf_counter() - t
    log.write_text(proc.stderr)
    if proc.returncode != 0:
        raise SystemExit(f"hgca drive failed ({proc.returncode}): {proc.stderr[-3000:]}")
    rss = [int(line.split()[1]) for line in proc.stderr.splitlines() if line.startswith("MAXRSS")]
    return {"wall_s": round(wall, 1), "driver_peak_rss_gib": round(rss[-1] / 2**30, 2)}


def summarise(out: Path, measured: dict) -> dict:
    doc = json.loads((out / "drive.json").read_text())
    workers: dict[str, int] = {}
    mine = [t for t in doc["tiles"] if t.get("run") == doc["runs"]]
    for t in mine:
        workers[t["worker"]] = max(workers.get(t["worker"], 0), t["peak_rss"])
    return {**measured, "tiles": len(doc["tiles"]), "computed": doc["timings"]["tiles_computed"],
            "tiles_s": doc["timings"]["tiles_s"], "engine_start_s": doc["timings"].get("engine_start_s", 0.0),
            "merge_s": doc["timings"]["merge_s"], "tiles_per_min": doc["timings"]["tiles_per_min"],
            "tile_s_mean": round(float(np.mean([t["seconds"] for t in mine])), 1),
            "worker_peak_rss_gib": sorted(round(v / 2**30, 2) for v in workers.values())}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stage", choices=("coarse", "full"), default="coarse")
    ap.add_argument("--spacing", type=float, default=8.0)
    ap.add_argument("--length", type=float, default=1000.0)
    ap.add_argument("--short", type=float, default=250.0)
    ap.add_argument("--work", type=Path, default=Path("/tmp/hgca_drive_bench"))
    ap.add_argument("--results", type=Path, default=REPO / "benchmarks" / "results")
    ap.add_argument("--scans-per-tile", type=int, default=5, help="as `hgca drive --scans-per-tile`")
    ap.add_argument("--name", default="drive", help="the page's name: RESULTS/NAME.{md,json,png}")
    ap.add_argument("--t1", type=int, default=None, help="coarse GCA steps per tile (default: the weights')")
    ap.add_argument("--weights", default=None, help="coarse weights (default: the shipped ones)")
    ap.add_argument("--until", default=None, help="UTC HH:MM: skip a run expected to end after it")
    ap.add_argument("--runs", default="long:2,short:2,short:1,long:1", help="DRIVE:WORKERS, in order")
    ap.add_argument("--gt-cache", type=Path, default=None, help="keep the tiles' ground truth here")
    ap.add_argument("--gt-only", action="store_true", help="fill --gt-cache for the long 2-worker run's tiles")
    ap.add_argument("--score-only", action="store_true",
                    help="score the long run in --work and write the page from --results' drive.json (and --add)")
    ap.add_argument("--add", type=Path, nargs="*", default=[], help="results JSONs of other runs to put on the page")
    ap.add_argument("--page-only", action="store_true",
                    help="rewrite drive.md from --results' drive.json (with drive_memory.json and drive_slab.json)")
    ap.add_argument("--threads", type=int, default=1,
                    help="torch threads per tile in every run (1: a shared machine's cores are busy; more threads "
                         "than free cores wait for each other)")
    args = ap.parse_args()
    deadline = None
    if args.until:
        h, m = map(int, args.until.split(":"))
        now = dt.datetime.now(dt.timezone.utc)
        deadline = now.replace(hour=h, minute=m, second=0).timestamp()
    if args.page_only:
        (args.results / f"{args.name}.md").write_text(
            table(json.loads((args.results / f"{args.name}.json").read_text()), args.results))
        return 0
    result = {"name": args.name, "machine": machine(), "threads_per_tile": args.threads,
              "scans_per_tile": args.scans_per_tile, "stage": args.stage, "t1": args.t1, "spacing_m": args.spacing,
              "drives": {}, "runs": {}, "skipped": []}
    built = {}
    for name, length in (("short", args.short), ("long", args.length)):
        t = time.perf_counter()
        folder = args.work / f"scans_{name}"
        done = folder / "built.json"         # the same drive built before (same length and spacing): reused
        if done.is_file() and json.loads(done.read_text())["asked"] == [length, args.spacing]:
            info = json.loads(done.read_text())
            scans, poses = sorted(folder.glob("scan_*.npz")), folder / "poses.json"
            placed = scenes(int(np.ceil((length + 4.0 - 116.0) / SCENE)) + 1)
        else:
            shutil.rmtree(folder, ignore_errors=True)
            scans, poses, got, placed = build_drive(folder, length, args.spacing)
            info = {"asked": [length, args.spacing], "length_m": round(got, 1), "scans": len(scans),
                    "build_s": round(time.perf_counter() - t, 1)}
            done.write_text(json.dumps(info))
        built[name] = (scans, poses, placed)
        result["drives"][name] = {k: info[k] for k in ("length_m", "scans", "build_s")}
        print(name, result["drives"][name], flush=True)
    tile_s: list[float] = []
    if args.gt_only or args.score_only:
        return score(args, built)
    for name, workers in [(r.split(":")[0], int(r.split(":")[1])) for r in args.runs.split(",")]:
        label = f"{result['drives'][name]['length_m']:.0f} m, {workers} worker{'s' * (workers > 1)}"
        scans, poses, _ = built[name]
        if deadline and tile_s:
            tiles = 2 + int(np.ceil((result["drives"][name]["length_m"] + 6.4 - 38.4) / 32.0))
            if time.time() + 1.15 * tiles * np.mean(tile_s) / workers + 60 > deadline:
                result["skipped"].append(label)
                continue
        out = args.work / f"{name}_w{workers}"
        shutil.rmtree(out, ignore_errors=True)
        run = run_cli([*scans, "--poses", poses, "--stage", args.stage, "--threads", args.threads, "--out", out,
                       *(["--t1", args.t1] if args.t1 else []), "--scans-per-tile", args.scans_per_tile,
                       "--workers", workers, *(["--weights", args.weights] if args.weights else [])],
                      args.work / f"{name}_w{workers}.log")
        result["runs"][label] = {"drive": name, "workers": workers, **summarise(out, run)}
        tile_s.append(result["runs"][label]["tile_s_mean"])
        print(label, result["runs"][label], flush=True)
        write(result, args.results)
    result["load_average"] = [round(v, 1) for v in os.getloadavg()]
    write(result, args.results)
    if any(v["drive"] == "long" for v in result["runs"].values()):
        return score(args, built)
    print(table(result, args.results))
    return 0


def score(args, built: dict) -> int:
    """Seams of the long drive's first run (its ground truth from --gt-cache where there), the page and the PNG;
    with --gt-only just the ground truth."""
    if args.gt_only:
        doc = json.loads((args.work / "long_w2" / "drive.json").read_text())
        for t in doc["tiles"]:
            ground_truth(Region.from_tuple(t["region"]), built["long"][2], cache=args.gt_cache)
        return 0
    result = json.loads((args.results / f"{args.name}.json").read_text())
    for extra in args.add:
        other = json.loads(extra.read_text())
        result["runs"].update(other["runs"])
        result["drives"].update({k: v for k, v in other["drives"].items() if k not in result["drives"]})
        result["skipped"] = [s for s in result["skipped"] if s not in other["runs"]]
    for name, w in [(r.split(":")[0], int(r.split(":")[1])) for r in args.runs.split(",")]:  # asked, not run
        label = f"{result['drives'][name]['length_m']:.0f} m, {w} worker{'s' * (w > 1)}"
        if label not in result["runs"] and label not in result["skipped"]:
            result["skipped"].append(label)
    long_runs = [v for v in result["runs"].values() if v["drive"] == "long"]
    workers = long_runs[0]["workers"] if long_runs else 2
    out = args.work / f"long_w{workers}"
    doc = json.loads((out / "drive.json").read_text())
    t = time.perf_counter()
    gts = [ground_truth(Region.from_tuple(t["region"]), built["long"][2], cache=args.gt_cache) for t in doc["tiles"]]
    if len(long_runs) == 2:
        a, b = (args.work / f"long_w{w}" / "drive_s0.ply" for w in (1, 2))
        result["ray_equals_in_process"] = a.read_bytes() == b.read_bytes()
    result["worker_growth"] = worker_growth(args.work)
    xs = np.array([s["position"][0] for s in doc["scans"]])
    result["seams"] = seam_scores(out, gts, float(xs.min()), float(xs.max()))
    result["seams"].update(slab_sources(result["seams"], doc))
    result["seams"]["scored_run"] = f"long drive, {workers} workers"
    result["seams"]["ground_truth_s"] = round(time.perf_counter() - t, 1)
    plot(out, args.results / f"{args.name}.png", result["seams"])
    result.setdefault("load_average", [round(v, 1) for v in os.getloadavg()])
    write(result, args.results)
    print(table(result, args.results))
    return 0


def write(result: dict, folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    name = result.get("name", "drive")
    (folder / f"{name}.json").write_text(json.dumps(result, indent=1))
    (folder / f"{name}.md").write_text(table(result, folder))


def table(r: dict, folder: Path | None = None) -> str:
    """The page; with `folder`, also what `drive_memory.py` and `drive_slab.py` wrote there."""
    m = r["machine"]
    d = r["drives"]
    lines = [f"# Whole-drive benchmark: `hgca drive` on {d['short']['length_m']:.0f} m and "
             f"{d['long']['length_m']:.0f} m, stage {r['stage']}, T1 = {r['t1'] or 'default'}", "",
             f"Machine: {m['cpu']}, {m['cores']} cores shared with other jobs (load average "
             f"{r.get('load_average', 'n/a')} at the end), torch {m['torch']}, {r['threads_per_tile']} torch "
             f"thread(s) per tile, {m['date']}. Synthetic drives along seeded city scenes ({d['short']['scans']} and "
             f"{d['long']['scans']} Waymo-profile scans every {r['spacing_m']} m), 38.4 m tiles overlapping 6.4 m, "
             f"{r.get('scans_per_tile', 5)} scans per tile.", "",
             "| run | tiles | wall (s) | Ray start (s) | tiles (s) | merge (s) | tiles/min | mean tile (s) | "
             "driver peak RSS (GiB) | worker peak RSS (GiB) |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for name, v in r["runs"].items():
        lines.append(f"| {name} | {v['tiles']} | {v['wall_s']} | {v['engine_start_s']} | {v['tiles_s']} | "
                     f"{v['merge_s']} | {v['tiles_per_min']} | {v['tile_s_mean']} | {v['driver_peak_rss_gib']} | "
                     f"{', '.join(map(str, v['worker_peak_rss_gib']))} |")
    for name in r["skipped"]:
        lines.append(f"| {name} | not run: it would have ended after the time set for the benchmark | | | | | | | | |")
    lines.append("")
    if r.get("t1"):
        lines.append(f"Stage {r['stage']} with T1 = {r['t1']} GCA steps per tile, fewer than the weights' own: a "
                     "light configuration for the seams and the workers' memory; "
                     "[drive_full.md](drive_full.md) runs `hgca drive` as it ships (stage full, the weights' steps).")
        lines.append("")
    g = r.get("worker_growth")
    if g:
        lines.append(f"Memory per Ray worker follows the tiles it has run, not the drive's length: after its first "
                     f"{g['n']} tiles a worker peaks at {g['short_at_n']} GiB on {d['short']['length_m']:.0f} m and "
                     f"{g['long_at_n']} GiB on {d['long']['length_m']:.0f} m; on the long drive it then creeps by "
                     f"{g['mib_per_tile']} MiB a tile (least squares over its tiles {g['n']} to {g['long_tiles']}), to "
                     f"{g['long_last']} GiB after {g['long_tiles']} tiles.")
        lines.append("")
    lines.append("The runs ran one after another while other jobs on the machine came and went, so their tiles "
                 "per minute compare only roughly.")
    lines.append("")
    lines.append("On 1 worker the tiles run in the driver process, so its peak RSS holds every scan of the drive as "
                 "well as one tile; a Ray worker holds one tile at a time.")
    if "ray_equals_in_process" in r:
        lines += ["", f"Ray's merged mesh is byte-identical to the in-process one: {r['ray_equals_in_process']}."]
    s = r.get("seams")
    if s:
        lines += ["", f"Seams ({s['scored_run']}), 20 cm cells of the merged result against the ground truth:", "",
                  "| IoU inside tiles | IoU in overlap bands | bands / inside | neighbours agree in overlaps (IoU) |",
                  "|---:|---:|---:|---:|",
                  f"| {s['iou_interior']} | {s['iou_band']} | {s['ratio']} | {s['neighbour_agreement']} |", "",
                  f"| per {SLAB:g} m slab, {ENDS:g} m from either end left out | worst | at x (m) | median | "
                  "worst / median |", "|---|---:|---:|---:|---:|"]
        for key, label in (("recall", "recall of the ground truth"), ("iou", "IoU")):
            w = s["slabs"][key]
            lines.append(f"| {label} | {w['worst']} | {w['at_x']} | {w['median']} | {w['ratio']} |")
        if "repeat_correlation" in s:
            street = (s["recall_median_seam_slabs"] >= 0.95 * s["recall_median_other_slabs"]
                      and s["repeat_correlation"] > 0.5)
            lines += ["", f"Slabs that hold an ownership seam ({s['seam_slabs']}) recover a median "
                      f"{s['recall_median_seam_slabs']} of the ground truth, the others "
                      f"{s['recall_median_other_slabs']}; a slab's recall correlates {s['repeat_correlation']} with "
                      f"the slab {2 * SCENE:g} m on (the street repeats its two layouts)"
                      + (": the weak slabs are places of the street, not seams." if street else ".")]
        lines += ["", "Overlap bands: places two tiles cover, scored on the tile that owns them in the merged mesh; "
                  "inside: places one tile covers. Ground truth: the scenes' surface a complete scan could see "
                  "(`synth.groundtruth.RegionSurface`), no visibility mask. Neighbour agreement: IoU of two "
                  "consecutive tiles' cells in their overlap (the second's mapped by cell centre into the first's "
                  "grid).", "", f"![drive]({r.get('name', 'drive')}.png)"]
    return "\n".join(lines + extra_sections(r, folder)) + "\n"


def extra_sections(r: dict, folder: Path | None) -> list[str]:
    """A Ray worker's memory tile after tile (`drive_memory.py`) and the worst slab without tiles
    (`drive_slab.py`), where their results are in `folder`."""
    lines: list[str] = []
    mem = folder / "drive_memory.json" if folder else None
    if mem and mem.is_file() and r.get("name", "drive") == "drive":
        d = json.loads(mem.read_text())
        lines += ["", f"## A worker's memory tile after tile ({d['length_m']:.0f} m, {d['tiles']} tiles on one Ray "
                  "worker, `drive_memory.py`)", "", "| code | RSS after first / last tile (MiB) | slope (MiB a tile): "
                  "resident | private | object-store pages |", "|---|---:|---:|---:|---:|"]
        for label, v in d["runs"].items():
            s = v["slope_mib_per_tile"]
            name = f"{label}: {v['code']}" if v["code"] else label
            lines.append(f"| {name} | {v['rows'][0]['VmRSS'] / 2**20:.0f} / "
                         f"{v['rows'][-1]['VmRSS'] / 2**20:.0f} | {s['VmRSS']} | {s['RssAnon']} | {s['RssShmem']} |")
        lines += ["", "The per-tile growth is in the pages of Ray's object store a worker has touched (its scans "
                  "read, its results written), counted in its resident set: the driver kept every result "
                  "referenced until the drive's end and put every scan in the store up front, so each tile's "
                  "objects landed on new pages. The driver now submits tiles along the drive, a few at a time, "
                  "and drops each object when no task still to be submitted needs it; the store reuses its pages. "
                  "Details: [drive_memory.md](drive_memory.md)."]
    slab = folder / "drive_slab.json" if folder else None
    if slab and slab.is_file() and r.get("seams") and r.get("name", "drive") == "drive":
        d = json.loads(slab.read_text())
        a = d["at_slab"]
        lines += ["", f"## The worst slab without tiles (x = {d['x']:g} m, `drive_slab.py`)", "",
                  f"One {TILE_M} m region centred on the slab, completed from its 5 nearest scans with no neighbour "
                  f"and no ownership cut (stage coarse, T1 = {d['t1']}, seeds "
                  f"{', '.join(str(u['seed']) for u in d['untiled'])}), scored the same way:", "",
                  "| slab at x (m) | tiled (1 km drive) | one region: median | min | max | drive's median slab |",
                  "|---:|---:|---:|---:|---:|---:|",
                  f"| {d['x']:g} | {a['tiled']} | {a['untiled_median']} | {a['untiled_min']} | {a['untiled_max']} | "
                  f"{d['drive_median']} |", ""]
        sx, sr = r["seams"]["slab_x"], r["seams"]["slab_recall"]
        repeats = [(d["x"] + k * 2 * SCENE, sr[sx.index(d["x"] + k * 2 * SCENE)]) for k in range(1, 8)
                   if d["x"] + k * 2 * SCENE in sx]
        if repeats:
            lines += [f"The same place of the street one or more repeats ({2 * SCENE:g} m) on, where the tiles fall "
                      "differently, recovers " + ", ".join(f"{v} (x = {x:g} m)" for x, v in repeats)
                      + " on the drive.", ""]
        med = d["drive_median"]
        lines.append(f"Completed alone, the slab recovers {a['untiled_median']} "
                     f"({a['untiled_median_over_drive_median']}x the drive's median slab) with every seed within "
                     f"{a['untiled_max'] - a['untiled_min']:.3f}"
                     + (": below 0.8x, so this place of the street is weak for the model itself, tiles or not."
                        if a["untiled_max"] < 0.8 * med else "."))
        lines.append("")
        tile = folder / "drive_slab_tile.json"
        if tile.is_file():
            t = json.loads(tile.read_text())
            at = t["slab_x"].index(d["x"])
            vals = [u["slab_recall"][at] for u in t["untiled"]]
            lines.append(f"The drive's own tile there (centre x = {t['x']:g} m, its 5 scans), completed alone "
                         f"without its neighbours' cells, recovers {min(vals)}-{max(vals)} in the slab "
                         f"(seeds {', '.join(str(u['seed']) for u in t['untiled'])}), against {a['tiled']} with them "
                         "in the drive: "
                         + ("where the tile sits (the slab "
                            f"{abs(d['x'] - t['x']):g} m off its centre, near its seam, from the scans around its "
                            "centre), not the neighbours' cells, takes the slab below the centred region."
                            if abs(float(np.median(vals)) - a["tiled"]) < abs(float(np.median(vals))
                                                                             - a["untiled_median"]) else
                            "the neighbours' cells, not where the tile sits, take the slab lower."))
        def others(t: dict) -> float:
            """Mean recall over the region's slabs other than the worst one's, over seeds."""
            return float(np.mean([v for u in t["untiled"] for x, v in zip(t["slab_x"], u["slab_recall"])
                                  if x != d["x"]]))

        base = json.loads(tile.read_text()) if tile.is_file() else None
        for more in sorted(folder.glob("drive_slab_tile_s*.json")):
            t = json.loads(more.read_text())
            vals = [u["slab_recall"][t["slab_x"].index(d["x"])] for u in t["untiled"]]
            lines.append(f"From its {t['scans_per_tile']} nearest scans instead (`--scans-per-tile "
                         f"{t['scans_per_tile']}`: scans along the tile's whole length at this spacing), the same "
                         f"tile alone recovers {min(vals)}-{max(vals)} in the slab "
                         f"({float(np.median(vals)) / med:.2f}x the drive's median slab), and a mean "
                         f"{others(t):.3f} over its other slabs"
                         + (f" against {others(base):.3f} from 5" if base else "") + ". The drive's figures above "
                         "are with 5 scans a tile.")
        lines += ["", "![worst slab alone](drive_slab.png)"]
    lines += more_scans(r, folder)
    return lines


def more_scans(r: dict, folder: Path | None) -> list[str]:
    """This drive against the same drive with more scans a tile (`--name drive_spt<N>` runs in `folder`)."""
    lines: list[str] = []
    for path in sorted(folder.glob("drive_spt*.json")) if folder and r.get("seams") else []:
        o = json.loads(path.read_text())
        if not o.get("seams"):
            continue
        rows = [(o, o["seams"])]
        if not lines:
            lines += ["", "## Scans a tile (the long drive, 2 workers)", "",
                      "| scans a tile | IoU inside tiles | bands / inside | median slab recall | worst / median | "
                      "mean tile (s) | worker peak RSS (GiB) |", "|---:|---:|---:|---:|---:|---:|---|"]
            rows.insert(0, (r, r["seams"]))
        for doc, s in rows:
            run = next(v for v in doc["runs"].values() if v["drive"] == "long" and v["workers"] == 2)
            lines.append(f"| {doc.get('scans_per_tile', 5)} | {s['iou_interior']} | {s['ratio']} | "
                         f"{s['slabs']['recall']['median']} | {s['slabs']['recall']['ratio']} | {run['tile_s_mean']} | "
                         f"{', '.join(map(str, run['worker_peak_rss_gib']))} |")
    if lines:
        lines += ["", "The same drive, tiles and seeds; only `--scans-per-tile` differs (page: "
                  + ", ".join(f"[{p.stem}.md]({p.stem}.md)" for p in sorted(folder.glob("drive_spt*.json"))) + ")."]
    return lines


if __name__ == "__main__":
    sys.exit(main())

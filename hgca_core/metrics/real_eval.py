"""The runner behind `hgca eval-real`: one real input -> its cases (whole input, height cuts) x methods,
scored with `hgca_core.metrics.realscan`, plus the renderings and the markdown tables.

Everything is scored in the input's default region (the box `hgca complete` picks: 38.4 x 38.4 x 8 m around
the first sensor origin, from 1 m below the estimated ground; turned by `--yaw`), so the ground lies at region-frame
z = 1 m.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
from tqdm import tqdm

from hgca_core.geometry.freespace import HALF, confident, observed_empty, ray_origins, swept
from hgca_core.geometry.region import BELOW_GROUND, Region
from hgca_core.geometry.voxel import COARSE, voxelize
from hgca_core.metrics.realscan import cut_scores, free_space_scores, generated_cells, summarise
from hgca_core.metrics.settings import RealEvalSettings

SPACING = 0.05  # surface sampling of meshes before voxelising them (as `hgca eval` does)
METHODS = ("input", "poisson", "gca", "hgca", "hgca-full")
NAMES = {"input": "input", "poisson": "Poisson (Open3D)", "gca": "GCA (no planner)", "hgca": "hGCA coarse",
         "hgca-full": "hGCA full"}
WAYMO_NA = ("not applicable: the paper's Waymo protocol needs 5 input scans plus further scans of the same "
            "place as pseudo ground truth; our real fixtures hold at most 2 sweeps per log")


def read_input(item: dict):
    """The scan of one input (a scan file, or a sequence folder, bag or E57), accumulated in its world frame."""
    from hgca_core.io.read import read_scans
    from hgca_core.io.sequence import is_sequence, read_sequence

    if is_sequence([item["path"]]):
        return read_sequence(item["path"], item["frames"], calibration=item["calibration"], topic=item.get("topic"))
    return read_scans([item["path"]])


def input_rays(item: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (N, 3), sensor origins (S, 3), each point's origin row (N,)) of one input, world frame: the rays
    its observed free space is walked along."""
    scan = read_input(item)
    origins = np.asarray(scan.origins, dtype=np.float64)
    return scan.points, origins, ray_origins(origins, scan.attributes, scan.points)


def _mesh_cells(mesh, region: Region, seed: int) -> np.ndarray:
    """20 cm cells of a world-frame mesh's surface, in the region frame."""
    import trimesh

    from hgca_core.metrics.surface import sample_surface

    if len(mesh.faces) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    local = trimesh.Trimesh(region.to_local(mesh.vertices), mesh.faces, process=False)
    return voxelize(sample_surface(local, SPACING, seed), COARSE, region.size)


def height_cut(local: np.ndarray, inside: np.ndarray, region: Region, h: float | None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """One case of an input in `region`'s frame: (mask of the points kept, the kept points' 20 cm cells in the
    region, the real cells cut away or None). `h` None keeps every point; else the points `h` m or more above the
    estimated ground go, and a cell that still holds a point below the cut does not count as cut away."""
    keep = np.ones(len(local), dtype=bool) if h is None else local[:, 2] < BELOW_GROUND + h
    cells = voxelize(local[keep & inside], COARSE, region.size)
    if h is None:
        return keep, cells, None
    away = voxelize(local[~keep & inside], COARSE, region.size)
    return keep, cells, generated_cells(away, cells, region.grid_shape(COARSE))


class Runner:
    """Runs each method on one input case and keeps sample 0's mesh of the best row for the renderings."""

    def __init__(self, settings: RealEvalSettings, region: Region, origins: np.ndarray) -> None:
        from hgca_core.models.weights import weights_files

        self.settings, self.region, self.origins = settings, region, origins
        # the files `weights_record` digests for the results' config: loaded from the same one decision
        c = settings.completion
        self.files = weights_files(["hgca-full", "gca"], c.weights, c.fine_weights, settings.noplanner_weights)
        self.k = c.samples
        self.kf = settings.full_samples or c.samples
        self.index: np.ndarray | None = None

    def _complete(self, pts: np.ndarray, samples: int, seed: int, stage: str, role: str):
        """`hgca_core.complete` (`pipeline.complete`) of `pts`, each point's ray from its own sensor origin
        (`self.index`, set per case by `cells`), as `hgca complete` does for the same scans."""
        from hgca_core.pipeline import complete

        config = self.settings.completion.with_(samples=samples, seed=seed, stage=stage, weights=self.files[role],
                                                fine_weights=self.files["fine"])
        return complete(pts, region=self.region, origins=self.origins, config=config, origin_index=self.index)

    def cells(self, method: str, pts: np.ndarray, full: bool, index: np.ndarray | None = None) -> dict[str, Any]:
        """{method row: (list of cell sets, seconds per completion, sample-0 mesh or None)}; `index` (N,): each
        point's row in the origins (None: the nearest origin)."""
        settings, region = self.settings, self.region
        seed = settings.completion.seed
        self.index = index
        local = region.to_local(pts)
        inside = region.contains_local(local)
        t = time.time()
        if method == "input":
            return {"input": ([voxelize(local[inside], COARSE, region.size)], 0.0, None)}
        if method == "poisson":
            from hgca_core.metrics.baselines import poisson_baseline

            mesh = poisson_baseline(local[inside], region.to_local(self.origins), n_threads=settings.threads)
            mesh.vertices = region.to_world(mesh.vertices)
            return {"poisson": ([_mesh_cells(mesh, region, seed)], time.time() - t, mesh)}
        if method == "gca":
            res = self._complete(pts, self.k, seed, "coarse", "noplanner")
            return {"gca": ([r.coarse_cells for r in res], (time.time() - t) / self.k, res[0].mesh)}
        # hgca (+ hgca-full): the full stage's coarse cells are the coarse row's samples (same seeds)
        rows: dict[str, Any] = {}
        coarse, meshes, seconds_full = [], [], 0.0
        if full:
            res = self._complete(pts, self.kf, seed, "full", "coarse")
            seconds_full = (time.time() - t) / self.kf
            coarse += [r.coarse_cells for r in res]
            cells_full = [_mesh_cells(r.mesh, region, seed + i) for i, r in enumerate(res)]
            rows["hgca-full"] = (cells_full, seconds_full, res[0].mesh)
            meshes = [r.mesh for r in res[:1]]
            del res
        t = time.time()
        extra = self.k - len(coarse)
        if extra > 0:
            res = self._complete(pts, extra, seed + len(coarse), "coarse", "coarse")
            coarse += [r.coarse_cells for r in res]
            meshes = meshes or [res[0].mesh]
            seconds_coarse = (time.time() - t) / extra
        else:
            seconds_coarse = float("nan")  # only measured inside the full stage's runs
        rows["hgca"] = (coarse[: self.k], seconds_coarse, meshes[0])
        return rows


def evaluate_input(item: dict, methods: list[str], cuts: list[float], full_cuts: list[float],
                   settings: RealEvalSettings,
                   out: Path, render: bool = True, done: dict | None = None,
                   saved: Callable[[dict], None] | None = None) -> dict[str, Any]:
    """All cases and methods of one input; writes its renderings beside `out`. Cases in `done` (an earlier
    run's result for this input, same settings) are kept, not recomputed; `saved(result)` is called after each
    case so an interrupted run loses at most one case."""
    pts, origins, index = input_rays(item)
    region = Region.around(pts, sensor=origins[0], yaw=float(np.radians(settings.yaw)))
    local = region.to_local(pts)
    inside = region.contains_local(local)
    shape = region.grid_shape(COARSE)
    t = time.time()
    empty = observed_empty(local, region.to_local(origins), index, shape)
    t_free = time.time() - t
    core = confident(empty)
    t = time.time()
    half = swept(local, region.to_local(origins), index, shape) >= HALF
    t_swept = time.time() - t
    ground = BELOW_GROUND  # region-frame height of the estimated ground
    result: dict[str, Any] = {
        "source": item["path"], "frames": item["frames"], "calibration": item["calibration"],
        "points": len(pts), "points_in_region": int(inside.sum()), "origins": len(origins),
        "region": list(region.as_tuple()),
        "freespace": {"seconds": t_free, "rays": len(pts), "empty_cells": int(empty.sum()),
                      "core_cells": int(core.sum()), "swept_cells": int(half.sum()), "swept_seconds": t_swept,
                      "grid": list(shape)},
        "cases": {},
    }
    if done and not np.allclose(done.get("region", []), result["region"], atol=1e-6):
        # another region (newer code places it differently): earlier cases would not be comparable
        tqdm.write(f"{item['name']}: region differs from the earlier run's, recomputing every case", file=sys.stderr)
        done = None
    runner = Runner(settings, region, origins)
    cases = [("full", None)] + [(f"cut_{h:g}", h) for h in sorted(cuts, reverse=True)]
    for case, h in tqdm(cases, desc=item["name"], unit="case", leave=False):
        if done and case in done.get("cases", {}):
            result["cases"][case] = done["cases"][case]
            continue
        keep, case_cells, away = height_cut(local, inside, region, h)
        case_pts = pts[keep]
        entry: dict[str, Any] = {"points": int((keep & inside).sum()), "rows": {}}
        if h is not None:
            cut_z = ground + h
            entry.update({"cut_height": h, "cut_z_region": cut_z, "cut_away_cells": len(away)})
        full = "hgca-full" in methods and (h is None or any(abs(h - c) < 1e-9 for c in full_cuts))
        meshes: dict[str, Any] = {}
        for method in dict.fromkeys("hgca" if m == "hgca-full" else m for m in methods):
            rows = runner.cells(method, case_pts, full=full and method == "hgca", index=index[keep])
            for row, (cell_sets, seconds, mesh) in rows.items():
                if row not in methods:
                    continue
                if h is None:
                    per = [free_space_scores(c, case_cells, empty, core, half) for c in cell_sets]
                else:
                    per = [cut_scores(c, case_cells, away, cut_z, empty, core, half) for c in cell_sets]
                entry["rows"][row] = {"k": len(cell_sets), "seconds_per_completion": seconds,
                                      "per_sample": per, "summary": summarise(per)}
                if mesh is not None:
                    meshes[row] = mesh
            del rows
        shown = next((m for m in ("hgca-full", "hgca", "gca", "poisson") if m in meshes), None)
        if render and shown is not None and (h is None or h == max(cuts)):
            png = out.with_name(f"{out.stem}_{item['name']}{'' if h is None else f'_cut{h:g}'}.png")
            _render(meshes[shown], region, local[keep & inside], png,
                    None if h is None else local[~keep & inside])
            entry["rendering"] = {"file": png.name, "mesh": shown}
        del meshes
        result["cases"][case] = entry
        if saved is not None:
            saved(result)
    if done:  # earlier cut levels not asked for now are kept too
        for case, entry in done.get("cases", {}).items():
            result["cases"].setdefault(case, entry)
    result["cases"] = dict(sorted(result["cases"].items(),
                                  key=lambda kv: -1.0 if kv[0] == "full" else float(kv[1]["cut_height"])))
    return result


def _render(mesh, region: Region, points_local: np.ndarray, png: Path, marked_local: np.ndarray | None) -> None:
    """Input yellow, observed grey, generated blue (distance to the input), cut-away points red."""
    import trimesh

    from hgca_core.geometry.nearest import PointIndex
    from hgca_core.render import render_mesh

    local = trimesh.Trimesh(region.to_local(mesh.vertices), mesh.faces, process=False)
    dist = PointIndex(points_local).distances(local.vertices) if len(points_local) else None
    centre = region.size / 2 * np.array([1.0, 1.0, 0.0]) + np.array([0.0, 0.0, BELOW_GROUND])
    eye = centre + np.array([-22.0, -30.0, 24.0])
    render_mesh(local, png, points=points_local, colour_by=dist, eye=eye, target=centre, marked=marked_local)


def _pct(s: dict | None, key: str, k: int) -> str:
    if s is None or key not in s or s[key]["mean"] is None or s[key]["mean"] != s[key]["mean"]:
        return "-"
    v = s[key]
    return f"{100 * v['mean']:.1f}" if k == 1 else f"{100 * v['mean']:.1f} [{100 * v['min']:.1f}–{100 * v['max']:.1f}]"


def _num(s: dict | None, key: str, k: int) -> str:
    if s is None or key not in s or s[key]["mean"] is None or s[key]["mean"] != s[key]["mean"]:
        return "-"
    v = s[key]
    return f"{v['mean']:,.0f}" if k == 1 else f"{v['mean']:,.0f} [{v['min']:,.0f}–{v['max']:,.0f}]"


def _secs(v) -> str:
    return "-" if v is None or v != v or v == 0 else f"{v:.0f}"


def _ordered(rows: dict) -> list:
    return sorted(rows.items(), key=lambda kv: METHODS.index(kv[0]))


def format_tables(results: dict) -> str:
    """Markdown: one table per measure, a row per input x (cut) x method; k samples as mean [min–max]."""
    cfg = results["config"]
    lines = ["# Completion of real scans, scored without ground truth", "",
             f"k = {cfg['samples']} samples for GCA / hGCA coarse, k = {cfg['full_samples']} for hGCA full "
             f"(seeds {cfg['seed']}..); values are mean [min–max] over the samples. "
             + (f"Full stage run on the whole input and at cut(s) {', '.join(f'{c:g} m' for c in cfg['full_cuts'])}"
                " only (CPU time); " if "hgca-full" in cfg.get("methods", ()) else "")
             + f"{cfg['threads']} thread(s), precision {cfg['precision']}, free space {cfg.get('free_space', 'auto')}. "
             "Cells are 20 cm, in the default region. "
             "Seconds are wall time on a 2-core machine shared with other jobs (only a rough guide; hGCA "
             "coarse samples that came out of a full-stage run have no time of their own).",
             "", "## Observed free space (whole input)", "",
             "Generated cells: completion cells the input does not occupy. In observed empty: the share of them "
             "that lie where an input ray passed (walked from the sensor to 0.4 m short of its hit, cells next "
             "to a hit excluded): the sensor saw through them. In its core: in the free cells whose six "
             "neighbours are free too; the free space's rim holds true surface where rays graze it. Swept: in the "
             "free cells whose volume the rays crossed at least half of (counted on 5 cm sub-cells): what the rays "
             "disproved rather than grazed. A perfect completion of a synthetic single sweep (64 val scenes) "
             "scores 0.9-14 % (mean 5.8 %) in the free space, 0-0.6 % in its core "
             "and 0-1.5 % swept.", "",
             "| input | method | k | generated cells | in observed empty (%) ↓ | in its core (%) ↓ "
             "| swept (%) ↓ | s / completion |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for name, res in results["inputs"].items():
        for row, r in _ordered(res["cases"].get("full", {}).get("rows", {})):
            s, k = r["summary"], r["k"]
            lines.append(f"| {name} | {NAMES[row]} | {k} | {_num(s, 'generated', k)} | "
                         f"{_pct(s, 'empty_share', k)} | {_pct(s, 'core_share', k)} | "
                         f"{_pct(s, 'swept_share', k)} | {_secs(r['seconds_per_completion'])} |")
    lines += ["", "## Height-cut extrapolation", "",
              "The input is cut h m above the estimated ground and completed. Recall: share of the real 20 cm "
              "cells that were cut away with a completion cell within one cell. Above the cut: generated cells "
              "above the cut, and the share of them in the whole input's observed free space, in its core and in "
              "its swept cells.", "",
              "| input | cut | method | k | cut-away cells | recall (%) ↑ | generated above cut | "
              "above cut in observed empty (%) ↓ | in its core (%) ↓ | swept (%) ↓ |",
              "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, res in results["inputs"].items():
        for case, entry in res["cases"].items():
            if case == "full":
                continue
            for row, r in _ordered(entry["rows"]):
                s, k = r["summary"], r["k"]
                lines.append(f"| {name} | {entry['cut_height']:g} m | {NAMES[row]} | {k} | "
                             f"{entry['cut_away_cells']:,} | {_pct(s, 'recall', k)} | "
                             f"{_num(s, 'generated_above', k)} | {_pct(s, 'above_empty_share', k)} | "
                             f"{_pct(s, 'above_core_share', k)} | {_pct(s, 'above_swept_share', k)} |")
    lines += ["", "## Inputs", "", "| input | source | points (in region) | observed-empty cells (core; swept) | "
              "ray walk, wall (s): 20 cm (5 cm) |", "|---|---|---:|---:|---:|"]
    for name, res in results["inputs"].items():
        src = Path(res["source"]).name + (f" frames {res['frames']}" if res["frames"] else "")
        if res["calibration"]:
            src += f" (lidar origins from {Path(res['calibration']).parents[1].name[:8]}'s calibration)"
        fs = res["freespace"]
        core = f"{fs['core_cells']:,}" if "core_cells" in fs else ""
        core += f"; {fs['swept_cells']:,}" if "swept_cells" in fs else ""
        walk = f"{fs['seconds']:.2f}" + (f" ({fs['swept_seconds']:.2f})" if "swept_seconds" in fs else "")
        lines.append(f"| {name} | {src} | {res['points']:,} ({res['points_in_region']:,}) | "
                     f"{fs['empty_cells']:,}{f' ({core})' if core else ''} | {walk} |")
    lines += ["", f"Paper's Waymo protocol (ReSim and IoU against the other scans of a drive): "
              f"{results['waymo_protocol']['reason']}.", ""]
    asked = set(results.get("config", {}).get("methods", METHODS))
    missing = [f"{NAMES[m]} at {name} {'whole input' if case == 'full' else case.replace('cut_', '') + ' m cut'}"
               for name, res in results["inputs"].items() for case, e in res["cases"].items()
               for m in METHODS if m in asked and m not in e["rows"] and (m != "hgca-full" or case == "full")]
    if missing:
        lines += ["Asked for but not run (the full stage runs only at --full-cuts): " + "; ".join(missing) + ".", ""]
    pngs = [e["rendering"]["file"] for r in results["inputs"].values() for e in r["cases"].values()
            if "rendering" in e]
    if pngs:
        lines += ["Renderings (input yellow, observed grey, generated blue, cut-away real points red): "
                  + ", ".join(f"[{p}]({p})" for p in pngs), ""]
    for note in results.get("notes", []):  # provenance added to the JSON by whoever ran it
        lines += [note, ""]
    if "total_seconds" in results:
        lines += [f"Total run time {results['total_seconds'] / 60:.1f} min.", ""]
    return "\n".join(lines)

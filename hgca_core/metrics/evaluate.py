"""Score k completions of one synthetic sample with every metric of the paper's Table 1, and print tables.

All geometry is in the sample's region frame (docs/CONTRACTS.md). Distances are metres here; only
`format_table` applies the paper's x10 display scale (and shows IoU in %).
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Mapping, Sequence

import numpy as np
import trimesh

from hgca_core.errors import InputError
from hgca_core.geometry.voxel import COARSE, voxelize
from hgca_core.metrics.iou import iou
from hgca_core.metrics.resim import default_sensor, resim_cd_per_pose, resim_scans
from hgca_core.metrics.street import GROUND_MARGIN, street_cd, street_penalty, street_points
from hgca_core.metrics.surface import sample_surface
from hgca_core.metrics.tmd import tmd

if TYPE_CHECKING:
    from hgca_core.geometry.raycast import Sensor

SCALAR_KEYS = ("resim_min", "resim_avg", "tmd", "iou", "street_cd_min", "street_cd_avg", "street_tmd")


def _street_face_mask(mesh: trimesh.Trimesh, box: np.ndarray, ground_z: float) -> np.ndarray:
    """Faces that can hold street-object points: x/y extent overlapping the box, top above the ground cut."""
    tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]
    lo, hi = tri.min(1), tri.max(1)
    return ((hi[:, 0] >= box[0]) & (lo[:, 0] < box[2]) & (hi[:, 1] >= box[1]) & (lo[:, 1] < box[3])
            & (hi[:, 2] > ground_z + GROUND_MARGIN))


def evaluate_sample(sample: Mapping[str, Any], meshes: Sequence[trimesh.Trimesh],
                    occ20: Sequence[np.ndarray] | None = None, sensor: "Sensor | None" = None,
                    spacing: float = 0.05, seed: int = 0) -> dict[str, Any]:
    """Metrics of k completions (`meshes`, region frame) of one sample, in metres (IoU as a fraction).

    - resim_min / resim_avg: High LiDAR ReSim CD over the k completions (each: mean over eval poses).
    - tmd: TMD of the re-simulated scans, per pose, averaged over poses (paper, App. eq. TMD_ReSim).
    - iou: mean over completions of the 20 cm IoU against `gt_occ20` within `visible20`; cells are
      `occ20[i]` when given (a voxel method's own occupancy), else the mesh surface sampled at `spacing`
      and voxelised like the ground truth.
    - street_cd_min / street_cd_avg / street_tmd: only when the sample has `street_box` (NaN otherwise).
    TMDs are NaN for k = 1. Per-completion values are returned too (`*_per_sample`).
    """
    k = len(meshes)
    if k == 0:
        raise InputError("evaluate_sample needs at least one completion mesh")
    if occ20 is not None and len(occ20) != k:
        raise InputError(f"{k} meshes but {len(occ20)} occupancy sets")
    missing = [key for key in ("region", "eval_poses", "gt_occ20") if key not in sample]
    missing += [f"eval_scan_{t}" for t in range(len(sample.get("eval_poses", []))) if f"eval_scan_{t}" not in sample]
    if missing:
        raise InputError(f"sample lacks {', '.join(missing)}")
    sen = default_sensor(sensor)
    region_size = np.asarray(sample["region"], dtype=np.float64)[3:6]
    poses = np.asarray(sample["eval_poses"], dtype=np.float64)
    gt_scans = [np.asarray(sample[f"eval_scan_{t}"], dtype=np.float64) for t in range(len(poses))]

    scans = [resim_scans(m, poses, sen, region_size) for m in meshes]           # k x P
    per_pose = np.stack([resim_cd_per_pose(s, gt_scans, sen.max_range, region_size) for s in scans])
    resim = per_pose.mean(axis=1)
    resim_tmd = (float(np.mean([tmd([scans[i][t] for i in range(k)], empty_penalty=sen.max_range)
                                for t in range(len(poses))])) if k > 1 else float("nan"))

    visible = sample.get("visible20")
    if occ20 is None:
        occ20 = [voxelize(sample_surface(m, spacing, seed + i), COARSE, region_size) for i, m in enumerate(meshes)]
    ious = np.array([iou(o, sample["gt_occ20"], visible) for o in occ20])

    street = np.full(k, np.nan)
    street_tmd = float("nan")
    if "street_box" in sample and "gt_surface" in sample:
        box = np.asarray(sample["street_box"], dtype=np.float64).reshape(4)
        gz = float(np.asarray(sample["ground_z"]))
        grid = sample.get("ground_height")                       # format 2: the ground of sloped streets
        lowest = gz if grid is None else float(np.min(grid))
        pts = [street_points(sample_surface(m, spacing, seed + i, _street_face_mask(m, box, lowest))
                             if len(m.faces) else np.zeros((0, 3)), box, gz, ground_grid=grid)
               for i, m in enumerate(meshes)]
        street = np.array([street_cd(p, sample["gt_surface"], box, gz, ground_grid=grid) for p in pts])
        if k > 1:
            street_tmd = tmd(pts, empty_penalty=street_penalty(box))

    return {
        "k": k,
        "resim_min": float(resim.min()), "resim_avg": float(resim.mean()), "tmd": resim_tmd,
        "iou": float(np.nanmean(ious)) if np.any(np.isfinite(ious)) else float("nan"),
        "street_cd_min": float(np.min(street)), "street_cd_avg": float(np.mean(street)), "street_tmd": street_tmd,
        "resim_per_sample": resim.tolist(), "resim_per_pose": per_pose.tolist(),
        "iou_per_sample": ious.tolist(), "street_cd_per_sample": street.tolist(),
    }


def aggregate(results: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Dataset row: NaN-aware mean of each scalar metric over samples (NaN = not defined for a sample), and
    the per-scene values under `per_scene` so that tables can show the spread over scenes."""
    if not results:
        raise InputError("nothing to aggregate")
    row: dict[str, Any] = {"k": int(min(r["k"] for r in results)), "n": len(results), "per_scene": {}}
    for key in SCALAR_KEYS:
        v = np.array([r.get(key, np.nan) for r in results], dtype=np.float64)
        row[key] = float(np.nanmean(v)) if np.any(np.isfinite(v)) else float("nan")
        row["per_scene"][key] = [float(x) for x in v]   # NaN survives json as NaN
    return row


def spread(row: Mapping[str, Any], key: str) -> float:
    """Sample standard deviation over scenes of one metric of a row (NaN without per-scene values or with
    fewer than two defined ones)."""
    v = np.array(row.get("per_scene", {}).get(key, []), dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(np.std(v, ddof=1)) if len(v) > 1 else float("nan")


def _fmt(value: Any, scale: float) -> str:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return "-"
    return f"{v * scale:.2f}" if np.isfinite(v) else "-"


def format_table(rows: Mapping[str, Mapping[str, Any]]) -> str:
    """Markdown table in the layout of the paper's Table 1: ReSim min/avg/TMD, IoU, Street CD min/avg/TMD.

    CD and TMD are shown x10 (metres, like the paper), IoU in %. Rows with k = 1 (deterministic methods)
    show only the min, like the paper's merged cells. The Street CD columns appear only when some row
    has them. A row may carry a "representation" string (e.g. "10cm^3", "implicit").
    """
    has_street = any(np.isfinite(float(r.get("street_cd_min", np.nan))) for r in rows.values())
    head = ["Method", "Representation", "ReSim min ↓", "ReSim avg ↓", "ReSim TMD ↑", "IoU (%) ↑"]
    if has_street:
        head += ["Street CD min ↓", "Street CD avg ↓", "Street CD TMD ↑"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join(["---", "---"] + ["---:"] * (len(head) - 2)) + "|"]
    for name, r in rows.items():
        single = int(r.get("k", 1)) <= 1
        cells = [name, str(r.get("representation", "-")), _fmt(r.get("resim_min"), 10),
                 "-" if single else _fmt(r.get("resim_avg"), 10), "-" if single else _fmt(r.get("tmd"), 10),
                 _fmt(r.get("iou"), 100)]
        if has_street:
            cells += [_fmt(r.get("street_cd_min"), 10), "-" if single else _fmt(r.get("street_cd_avg"), 10),
                      "-" if single else _fmt(r.get("street_tmd"), 10)]
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    lines.append("CD and TMD x10 in metres (as in the paper), IoU in % at 20 cm over visible cells.")
    spread_rows = {name: r for name, r in rows.items() if r.get("per_scene")}
    if spread_rows:
        keys = ["resim_min", "resim_avg", "tmd", "iou"] + (["street_cd_min", "street_cd_avg", "street_tmd"]
                                                           if has_street else [])
        scales = {"iou": 100}
        lines += ["", "Spread over scenes: standard deviation of the per-scene values (same units; the mean is the "
                  "table above).", "", lines[0].replace("Representation", "Scenes"), lines[1]]
        for name, r in spread_rows.items():
            single = int(r.get("k", 1)) <= 1
            cells = [name, str(len(r["per_scene"].get("iou", [])))]
            for key in keys:
                hidden = single and key in ("resim_avg", "tmd", "street_cd_avg", "street_tmd")
                cells.append("-" if hidden else _fmt(spread(r, key), scales.get(key, 10)))
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)

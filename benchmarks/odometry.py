"""Poses from the scans (`hgca poses --estimate`, KISS-ICP odometry) against true poses, and what they do to a
completion.

Measured: the drift of the estimated poses (translation error per metre travelled, rotation error in degrees per
metre) on the Argoverse 2 log of tests/data/real (2 sweeps, true poses from its city_SE3_egovehicle table) and on
a simulated drive (a synthetic street scanned by a spinning 64-beam sensor that moves and turns during each sweep:
raw, motion-distorted sweeps with per-point times, as a real sensor gives them); and the "done means": the AV2
sweeps with their poses removed, `hgca poses --estimate`, `hgca complete --stage coarse`, against the completion
from the true poses (same seed and region): the chamfer distance between the two meshes' surfaces, beside the
chamfer between two seeds of the true-pose completion (the seed band). Writes benchmarks/results/odometry.{json,md,png}.

    .venv/bin/python benchmarks/odometry.py

The simulated drive is the tests' (`simulate_drive` of tests/builders.py, which tests/io/test_odometry.py uses too).
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
AV2_LOG = REPO / "tests" / "data" / "real" / "av2" / "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"


def pose_error(truth: np.ndarray, est: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) of truth^-1 est."""
    d = np.linalg.inv(truth) @ est
    return float(np.linalg.norm(d[:3, 3])), float(np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1))))


def drift(truth: list[np.ndarray], est: list[np.ndarray]) -> dict:
    """End-point and worst-frame errors of a trajectory (both with frame 0 = identity), per metre travelled."""
    travelled = float(sum(np.linalg.norm(b[:3, 3] - a[:3, 3]) for a, b in zip(truth, truth[1:])))
    end_t, end_r = pose_error(truth[-1], est[-1])
    steps = [pose_error(np.linalg.inv(truth[i]) @ truth[i + 1], np.linalg.inv(est[i]) @ est[i + 1])
             for i in range(len(truth) - 1)]
    yaw = [float(np.degrees(np.arctan2(p[1, 0], p[0, 0]))) for p in truth]
    still_t, still_r = pose_error(truth[-1], np.eye(4))
    return {"identity_end_m": still_t, "identity_end_deg": still_r, "frames": len(truth), "travelled_m": travelled,
            "turned_deg": max(yaw) - min(yaw),
            "end_translation_m": end_t, "end_rotation_deg": end_r,
            "translation_pct": 100.0 * end_t / travelled, "rotation_deg_per_m": end_r / travelled,
            "worst_step_translation_m": max(s[0] for s in steps), "worst_step_rotation_deg": max(s[1] for s in steps),
            "true_xy": [p[:2, 3].tolist() for p in truth], "estimated_xy": [p[:2, 3].tolist() for p in est]}


def hgca(*args: object) -> float:
    """Run one `hgca` command (fails loudly); its CPU seconds (user + sys of the child)."""
    before = os.times()
    res = subprocess.run([sys.executable, "-m", "hgca_core.cli", *map(str, args)], capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"hgca {' '.join(map(str, args))} failed:\n{res.stderr[-3000:]}")
    after = os.times()
    return (after.children_user - before.children_user) + (after.children_system - before.children_system)


def surface(mesh_path: Path, count: int, seed: int) -> np.ndarray:
    import trimesh

    mesh = trimesh.load(mesh_path, force="mesh")
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(points, dtype=np.float64)


def av2_done_means(work: Path, seed: int, samples: int) -> dict:
    """The AV2 sweeps with their poses removed, `hgca poses --estimate`, a coarse completion; against the
    completion from the true poses (frame 0's ego frame for both, so the default region is the same)."""
    from hgca_core.io.sequence import open_sequence
    from hgca_core.metrics import chamfer

    truth_seq = open_sequence(AV2_LOG)
    est_dir, true_dir = work / "estimated", work / "true"
    for d in (est_dir, true_dir):
        d.mkdir()
        for f in truth_seq.files:
            shutil.copy(f, d)
    cpu = {"estimate": hgca("poses", "--estimate", est_dir, "-o", est_dir / "poses.json", "--progress", "none")}
    rel = [np.linalg.inv(truth_seq.poses[0]) @ p for p in truth_seq.poses]
    (true_dir / "poses.json").write_text(json.dumps({"scans": [
        {"file": Path(f).name, "pose": m.tolist()} for f, m in zip(truth_seq.files, rel)]}))
    common = ("--stage", "coarse", "--seed", seed, "--progress", "none")
    cpu["complete_estimated"] = hgca("complete", est_dir, "-o", work / "est.ply", *common)
    cpu["complete_true"] = hgca("complete", true_dir, "-o", work / "true.ply", "--samples", samples, *common)
    doc = json.loads((est_dir / "poses.json").read_text())
    est = [np.asarray(e["pose"]) for e in doc["scans"]]
    n = 200_000
    true_pts = [surface(work / f"true_s{i}.ply", n, 7 + i) for i in range(samples)]
    est_pts = surface(work / "est_s0.ply", n, 7)
    band = [chamfer(true_pts[0], true_pts[i]) for i in range(1, samples)]
    return {"drift": drift(rel, est), "estimated": doc["estimated"], "cpu_s": cpu,
            "chamfer_estimated_vs_true_m": chamfer(est_pts, true_pts[0]), "chamfer_seed_band_m": band,
            "surface_points": n, "seed": seed}


def synthetic(seed: int, frames: int) -> dict:
    from builders import simulate_drive   # tests/builders.py (benchmarks/common.py, imported by main, adds tests/)
    from hgca_core.io.odometry import estimate

    t0 = time.process_time()
    scans, poses, times, names = simulate_drive(seed=seed, frames=frames)
    t1 = time.process_time()
    found = estimate(scans, times, names)
    t2 = time.process_time()
    truth = [np.linalg.inv(poses[0]) @ p for p in poses]
    return {"drift": drift(truth, found.poses), "estimated": found.record(), "scene_seed": seed,
            "cpu_s": {"simulate": t1 - t0, "estimate": t2 - t1},
            "points_per_sweep": int(np.median([len(s) for s in scans]))}


def main() -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from common import write_page

    import kiss_icp

    start = time.process_time()
    with tempfile.TemporaryDirectory(prefix="hgca_odometry_") as tmp:
        av2 = av2_done_means(Path(tmp), seed=0, samples=2)
    syn = synthetic(seed=3, frames=20)
    cpu = time.process_time() - start + sum(av2["cpu_s"].values())
    result = {"kiss_icp": kiss_icp.__version__, "av2": av2, "synthetic": syn, "cpu_total_s": cpu,
              "date": time.strftime("%Y-%m-%d")}
    print(write_page(REPO / "benchmarks" / "results", "odometry", result, page, plot))


def page(r: dict) -> str:
    a, s = r["av2"], r["synthetic"]
    ad, sd = a["drift"], s["drift"]
    band = a["chamfer_seed_band_m"]
    rows = [("Argoverse 2 log 7fab2350 (real, 2 sweeps, no per-point times)", ad, a["estimated"]["settings"]),
            (f"synthetic street (scene seed {s['scene_seed']}, {sd['frames']} raw sweeps, per-point times, "
             "rolling shutter)", sd, s["estimated"]["settings"])]
    lines = [
        "# Poses from the scans: KISS-ICP odometry against true poses",
        "",
        f"`python benchmarks/odometry.py` ({r['date']}, kiss-icp {r['kiss_icp']}, {r['cpu_total_s']:.0f} s of CPU in "
        "all): `hgca poses --estimate` (hgca_core/io/odometry.py) on sweeps whose true poses are known. Drift = the "
        "last frame's pose error (both trajectories start at identity) per metre travelled; a step = one frame to "
        "the next. Every number below is measured by the script.",
        "",
        "| sequence | frames | travelled (m) | turned (deg) | end error (m) | translation drift (% of distance) | "
        "end rotation error (deg) | rotation drift (deg/m) | worst step (m / deg) | voxel (m) | deskew |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for name, d, st in rows:
        lines.append(f"| {name} | {d['frames']} | {d['travelled_m']:.3f} | {d['turned_deg']:.2f} | "
                     f"{d['end_translation_m']:.3f} | {d['translation_pct']:.1f} | {d['end_rotation_deg']:.3f} | "
                     f"{d['rotation_deg_per_m']:.3f} | {d['worst_step_translation_m']:.3f} / "
                     f"{d['worst_step_rotation_deg']:.3f} | {st['voxel_size']} | {'yes' if st['deskew'] else 'no'} |")
    lines += [
        "",
        f"The AV2 car moves only {ad['travelled_m'] * 100:.1f} cm between its two sweeps, so the per-metre figures "
        f"of that row are large although the error is {ad['end_translation_m'] * 100:.1f} cm and "
        f"{ad['end_rotation_deg']:.3f} deg: identity poses would be off by {ad['identity_end_m'] * 100:.1f} cm and "
        f"{ad['identity_end_deg']:.3f} deg. The synthetic drive runs 10 m/s with a sideways weave, so its "
        "sweeps are smeared by the sensor's own motion as raw sweeps are; KISS-ICP deskews them from the per-point "
        "times, and hgca moves each pose to its sweep's start time.",
        "",
        "## Done means: a completion from estimated poses",
        "",
        "The AV2 log's two sweeps copied to a folder without their poses, `hgca poses --estimate sweeps/ -o "
        "sweeps/poses.json`, then `hgca complete sweeps/ --stage coarse --seed 0` (the default region around the "
        "first sweep's sensor); against the same completion with the true poses (the log's own, relative to frame "
        "0, so both live in frame 0's ego frame and the default region is the same). Chamfer distance between "
        f"the two meshes' surfaces ({a['surface_points']:,} points sampled from each, trimesh; "
        "`hgca_core.metrics.chamfer`, the mean of both directions), beside the seed band: the same distance "
        "between the true-pose completions of seeds 0 and 1 (one run, --samples 2).",
        "",
        "| comparison | chamfer (m) |",
        "|---|---:|",
        f"| estimated poses (seed 0) vs true poses (seed 0) | {a['chamfer_estimated_vs_true_m']:.4f} |",
        *[f"| seed band: true poses, seed 0 vs seed {i + 1} | {b:.4f} |" for i, b in enumerate(band)],
        "",
        ("The estimated poses change the completion less than a different seed does."
         if a["chamfer_estimated_vs_true_m"] < min(band) else
         "The estimated poses change the completion more than a different seed does."),
        "",
        f"CPU (s): estimate {a['cpu_s']['estimate']:.1f}, completion from estimated poses "
        f"{a['cpu_s']['complete_estimated']:.1f}, from true poses (2 samples) {a['cpu_s']['complete_true']:.1f}; "
        f"synthetic: simulate {s['cpu_s']['simulate']:.1f}, estimate {s['cpu_s']['estimate']:.1f} "
        f"({s['points_per_sweep']:,} points per sweep).",
        "",
        "![trajectories from above](odometry.png)",
        "",
        "Per-frame checks of the synthetic run (fitness: share of registration points within "
        f"{s['estimated']['settings']['fit_distance']} m of the map; constraint: the smallest eigenvalue of the "
        "normalised point-to-plane information, ~0 in a corridor):",
        "",
        "| frame | fitness | rmse (m) | constraint |",
        "|---:|---:|---:|---:|",
        *[f"| {i} | {f['fitness']:.3f} | {f['rmse_m']:.3f} | {f['constraint']:.3f} |"
          for i, f in enumerate(s["estimated"]["frames"]) if "fitness" in f],
        "",
    ]
    return "\n".join(lines)


def plot(r: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6))
    for ax, (title, d) in zip(axes, (("Argoverse 2 log 7fab2350 (2 sweeps)", r["av2"]["drift"]),
                                     (f"synthetic street ({r['synthetic']['drift']['frames']} sweeps)",
                                      r["synthetic"]["drift"]))):
        t, e = np.asarray(d["true_xy"]), np.asarray(d["estimated_xy"])
        ax.plot(t[:, 0], t[:, 1], "o-", color="black", label="true", markersize=4)
        ax.plot(e[:, 0], e[:, 1], "x--", color="tab:red", label="estimated (KISS-ICP)", markersize=6)
        ax.set_title(f"{title}\nend error {d['end_translation_m']:.3f} m, {d['end_rotation_deg']:.2f} deg")
        ax.set_xlabel("x (m, frame 0)")
        ax.set_ylabel("y (m, frame 0)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()

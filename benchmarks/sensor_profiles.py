"""Real sweeps beside simulated ones of the same sensor profile: returns per ring, where each downward ring
meets the ground, ring spacing against range, and the range histogram.

    python benchmarks/sensor_profiles.py [--scenes 6] [--out benchmarks/results]

Real: the nuScenes sweep (HDL-32E) and the three Argoverse 2 sweeps (two VLP-32C) in tests/data/real.
Simulated: one scan per synthetic street (seeds 3,000,000 + i, the city style) with every real-sensor effect,
for all five profiles (KITTI's HDL-64E, Waymo and the OS1-128 have no real fixture here). It also
re-measures the AV2 beam table and mounting height the `av2` profile was built from.
Writes sensor_profiles.png, .md and .json.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from common import REPO


def ring_stats(local: np.ndarray, ring: np.ndarray, elev: np.ndarray, n_azimuth: int, ground_z: float) -> dict:
    """Per beam (sorted by elevation): returns per firing, and for downward beams the median horizontal
    distance of its ground points (within 15 cm of `ground_z`, sensor frame)."""
    order = np.argsort(elev)[::-1]
    rows = []
    horiz = np.linalg.norm(local[:, :2], axis=1)
    on_ground = np.abs(local[:, 2] - ground_z) < 0.15
    for k in order:
        m = ring == k
        g = m & on_ground
        rows.append({"beam": int(k), "elevation": float(elev[k]), "returns_per_firing": float(m.sum() / n_azimuth),
                     "ground_radius": float(np.median(horiz[g])) if elev[k] < -0.5 and g.sum() >= 20 else None})
    return {"rows": rows, "points": int(len(local)), "range_p50": float(np.median(np.linalg.norm(local, axis=1))),
            "range_p95": float(np.percentile(np.linalg.norm(local, axis=1), 95)),
            "horizontal": np.histogram(horiz, bins=np.arange(0, 101, 2.5))[0].tolist()}


def real_stats() -> dict:
    from builders import av2_sweeps, elevations, nuscenes_sweep

    from hgca_core.geometry.region import estimate_ground
    from hgca_core.synth.lidar import _AV2_DOWN, _AV2_UP, HDL32E

    out = {}
    nus = nuscenes_sweep()
    g = estimate_ground(nus.points, np.zeros(2))
    # nuScenes numbers its rings from the lowest beam up; the sensor is level
    el = np.array([np.median(elevations(nus.points[nus.ring == k], np.zeros(3))) for k in range(32)])
    out["hdl32"] = {"name": nus.name, "ground_z": g, "height": -g, **ring_stats(nus.points, nus.ring, el,
                                                                                   HDL32E.n_azimuth, g)}
    out["hdl32"]["beam_table_error_deg"] = float(np.max(np.abs(np.sort(el) - np.sort(HDL32E.elevations_deg))))
    sweeps = av2_sweeps()
    tables, heights, stats = [], [], []
    for sw in sweeps:
        up = (sw.points - _AV2_UP[:3, 3]) @ _AV2_UP[:3, :3]           # upper head frame (the rig frame)
        el = np.zeros(64)
        for k in range(64):
            m = sw.ring == k
            rot = _AV2_UP[:3, :3] if k < 32 else _AV2_DOWN[:3, :3]
            org = _AV2_UP[:3, 3] if k < 32 else _AV2_DOWN[:3, 3]
            far = np.linalg.norm(sw.points[m] - org, axis=1) > 3.0
            el[k] = np.median(elevations(sw.points[m][far], org, rot))   # each laser in its own head's frame
        tables.append(el)
        road = np.median(sw.points[sw.ring == 31, 2])                   # -25 deg upper beam: a ring on the road
        heights.append(float(_AV2_UP[2, 3] - road))
        el_rig = np.array([np.median(elevations(up[sw.ring == k], np.zeros(3))) for k in range(64)])
        stats.append(ring_stats(up, sw.ring, el_rig, 1800, road - _AV2_UP[2, 3]))
    table = np.median(tables, axis=0)
    out["av2"] = {"name": "AV2 (3 sweeps, first shown)", "height": float(np.median(heights)),
                  "heights": heights, "beam_table_up": table[:32].round(3).tolist(),
                  "beam_table_down": table[32:].round(3).tolist(), **stats[0]}
    return out


def sim_stats(profile: str, seeds: list[int]) -> dict:
    from hgca_core.geometry.raycast import make_intersector
    from hgca_core.synth.dataset import Drive
    from hgca_core.synth.lidar import PROFILES, Effects, Unit, scan
    from hgca_core.synth.scene import make_scene

    prof = PROFILES[profile]
    per, t_scan = [], []
    for seed in seeds:
        scene = make_scene(seed, "city")
        rng = np.random.default_rng(seed)
        drive = Drive(scene.drive, scene.drive_up)
        s = drive.length / 2
        unit = Unit.draw(prof, rng, Effects())
        t = time.perf_counter()
        sc = scan(make_intersector(scene.mesh), scene.face_materials, drive.pose(s), unit, rng, Effects(),
                  drive.pose(s + 6.0 / prof.rate_hz))
        t_scan.append(time.perf_counter() - t)
        local = (sc.points - sc.pose[:3, 3]) @ sc.pose[:3, :3]
        ground = float(scene.terrain.height(sc.pose[:2, 3])[0] - sc.pose[2, 3])
        el = np.concatenate([h.sensor.elevations_deg if abs(h.mount[2, 2] - 1) < 0.5 else
                             -h.sensor.elevations_deg for h in prof.heads])   # a head hung upside down looks up
        per.append(ring_stats(local, sc.ring, el, prof.heads[0].sensor.n_azimuth, ground))
    rows = []
    for i, r in enumerate(per[0]["rows"]):
        radii = [p["rows"][i]["ground_radius"] for p in per if p["rows"][i]["ground_radius"] is not None]
        rows.append({**r, "returns_per_firing": float(np.mean([p["rows"][i]["returns_per_firing"] for p in per])),
                     "ground_radius": float(np.median(radii)) if radii else None})
    return {"name": f"simulated {prof.name} ({prof.dataset})", "height": prof.height, "rows": rows,
            "points": float(np.mean([p["points"] for p in per])),
            "range_p50": float(np.mean([p["range_p50"] for p in per])),
            "range_p95": float(np.mean([p["range_p95"] for p in per])),
            "horizontal": np.mean([p["horizontal"] for p in per], axis=0).tolist(), "scan_s": float(np.median(t_scan))}


def spacing(rows: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """(radius, gap to the next ring out) of consecutive downward rings on the ground."""
    r = np.sort([x["ground_radius"] for x in rows if x["ground_radius"] is not None])
    return r[:-1], np.diff(r)


def plot(real: dict, sim: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(18, 10), dpi=90)
    colors = {"hdl32": "tab:blue", "av2": "tab:red", "hdl64": "tab:green", "waymo": "tab:purple", "os128": "tab:orange"}
    for key, st in sim.items():
        c = colors[key]
        el = [r["elevation"] for r in st["rows"]]
        axes[0, 0].plot(el, [r["returns_per_firing"] for r in st["rows"]], "-", color=c, lw=1, label=st["name"])
        rad = [(r["elevation"], r["ground_radius"]) for r in st["rows"] if r["ground_radius"]]
        if rad:
            axes[0, 1].plot(*zip(*rad), "-", color=c, lw=1, label=st["name"])
        axes[0, 2].plot(*spacing(st["rows"]), "-", color=c, lw=1, label=st["name"])
        axes[1, 0].plot(np.arange(0, 100, 2.5) + 1.25, st["horizontal"], "-", color=c, lw=1, label=st["name"])
    for key, st in real.items():
        c = colors[key]
        el = [r["elevation"] for r in st["rows"]]
        axes[0, 0].plot(el, [r["returns_per_firing"] for r in st["rows"]], "o", color=c, ms=4, label="real " + st["name"])
        rad = [(r["elevation"], r["ground_radius"]) for r in st["rows"] if r["ground_radius"]]
        axes[0, 1].plot(*zip(*rad), "o", color=c, ms=4, label="real " + st["name"])
        axes[0, 2].plot(*spacing(st["rows"]), "o", color=c, ms=4, label="real " + st["name"])
        axes[1, 0].plot(np.arange(0, 100, 2.5) + 1.25, st["horizontal"], "o", color=c, ms=4, label="real " + st["name"])
    axes[0, 0].set(xlabel="beam elevation (deg)", ylabel="returns per firing", title="points per ring (lines: simulated)")
    axes[0, 1].set(xlabel="beam elevation (deg)", ylabel="ground radius (m)", yscale="log",
                   title="where each downward ring meets the ground")
    axes[0, 2].set(xlabel="ring radius on the ground (m)", ylabel="gap to the next ring (m)", xscale="log",
                   yscale="log", title="ground ring spacing vs range")
    axes[1, 0].set(xlabel="horizontal range (m)", ylabel="points per 2.5 m bin", title="range histogram")
    for ax in axes.flat[:4]:
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    _bev(axes[1, 1], axes[1, 2], path)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _bev(ax_real, ax_sim, path: Path) -> None:
    """Top views: the real nuScenes sweep and a simulated HDL-32E sweep, 40 m around the sensor."""
    from builders import nuscenes_sweep

    from hgca_core.geometry.raycast import make_intersector
    from hgca_core.synth.dataset import Drive
    from hgca_core.synth.lidar import PROFILES, Effects, Unit, scan
    from hgca_core.synth.scene import make_scene

    nus = nuscenes_sweep()
    scene = make_scene(3_000_000, "city")
    rng = np.random.default_rng(0)
    drive = Drive(scene.drive, scene.drive_up)
    unit = Unit.draw(PROFILES["hdl32"], rng, Effects())
    sc = scan(make_intersector(scene.mesh), scene.face_materials, drive.pose(drive.length / 2), unit, rng, Effects())
    local = (sc.points - sc.pose[:3, 3]) @ sc.pose[:3, :3]
    for ax, pts, title in ((ax_real, nus.points, "real nuScenes HDL-32E sweep"),
                           (ax_sim, local, "simulated HDL-32E sweep (city street)")):
        m = np.all(np.abs(pts[:, :2]) < 40, axis=1)
        ax.scatter(pts[m, 0], pts[m, 1], s=0.2, c=np.clip(pts[m, 2], -2.5, 3), cmap="viridis", linewidths=0)
        ax.set(aspect="equal", xlim=(-40, 40), ylim=(-40, 40), title=f"{title}: {m.sum():,} points within 40 m")


def table(real: dict, sim: dict, meta: dict) -> str:
    lines = ["# Sensor profiles: real sweeps beside simulated ones", "",
             f"Measured by `benchmarks/sensor_profiles.py` ({meta['date']}, {meta['scenes']} simulated city streets "
             "per profile, one scan each, every real-sensor effect on). Ring radius: median horizontal distance at "
             "which a downward beam meets the ground. Spacing: median gap between neighbouring ground rings 8-25 m out.",
             "", "| sweep | beams | height (m) | points | returns/firing (all beams) | lowest ring radius (m) "
             "| ring spacing 8-25 m (m) | range p50 / p95 (m) |", "|---|---|---|---|---|---|---|---|"]
    for key, st in [(k, v) for k, v in real.items()] + [(k, v) for k, v in sim.items()]:
        radii = [r["ground_radius"] for r in st["rows"] if r["ground_radius"]]
        rr, gap = spacing(st["rows"])
        mid = gap[(rr > 8) & (rr < 25)]
        label = ("real " if st in real.values() else "") + st["name"]
        lines.append(f"| {label} | {len(st['rows'])} | {st['height']:.2f} | {st['points']:,.0f} | "
                     f"{np.mean([r['returns_per_firing'] for r in st['rows']]):.2f} | "
                     f"{min(radii) if radii else float('nan'):.2f} | "
                     f"{np.median(mid) if len(mid) else float('nan'):.2f} | {st['range_p50']:.1f} / {st['range_p95']:.1f} |")
    av2 = real.get("av2")
    if av2:
        lines += ["", f"AV2 mounting measured from the sweeps: upper VLP-32C {av2['height']:.3f} m above the road "
                  f"(per sweep {', '.join(f'{h:.3f}' for h in av2['heights'])}; profile: {meta['av2_height']:.2f} m). "
                  f"Beam table: largest difference between the measured per-laser elevations and the profile's "
                  f"{meta['av2_table_error']:.3f} deg (upper head), {meta['av2_table_error_down']:.3f} deg (lower head, "
                  "its own frame).",
                  f"nuScenes HDL-32E: measured ring elevations within {real['hdl32']['beam_table_error_deg']:.3f} deg "
                  "of the profile's table."]
    lines += ["", "Simulated scan time (one core, median): " + ", ".join(
        f"{k} {v['scan_s']:.2f} s" for k, v in sim.items()), ""]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=6)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results"))
    args = ap.parse_args()
    from hgca_core.synth.lidar import AV2_UP_HEIGHT, VLP32C

    real = real_stats()
    seeds = [3_000_000 + i for i in range(args.scenes)]
    sim = {k: sim_stats(k, seeds) for k in ("hdl32", "av2", "hdl64", "waymo", "os128")}
    meta = {"date": time.strftime("%Y-%m-%d"), "scenes": args.scenes, "av2_height": AV2_UP_HEIGHT,
            "av2_table_error": float(np.max(np.abs(np.array(real["av2"]["beam_table_up"]) - VLP32C.elevations_deg))),
            "av2_table_error_down": float(np.max(np.abs(np.array(real["av2"]["beam_table_down"]) - VLP32C.elevations_deg)))}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plot(real, sim, out / "sensor_profiles.png")
    (out / "sensor_profiles.md").write_text(table(real, sim, meta))
    (out / "sensor_profiles.json").write_text(json.dumps({"meta": meta, "real": real, "simulated": sim}, indent=1))
    print((out / "sensor_profiles.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())

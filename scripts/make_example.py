"""Regenerate the bundled example in hgca_core/examples/ (run by hand; the files are committed).

Five simulated 64-beam scans of one street (seed 3_000_001, outside the train/val/test seed ranges),
each cropped to 6 m around the default completion region so the package stays small, stored as LAZ in
the sensor frame (1 mm quantisation) with the poses JSON `hgca complete --poses` reads.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import laspy
import numpy as np

from hgca_core.synth.dataset import simulate

SEED = 3_000_001
OUT = Path(__file__).resolve().parents[1] / "hgca_core" / "examples"


def main() -> int:
    sim = simulate(SEED, 5)
    OUT.mkdir(parents=True, exist_ok=True)
    entries = []
    for i, (pts, pose) in enumerate(zip(sim.scans_world, sim.poses_world)):
        local_region = sim.region.to_local(pts)
        keep = np.all((local_region > -6.0) & (local_region < sim.region.size + 6.0), axis=1)
        sensor = (pts[keep] - pose[:3, 3]) @ pose[:3, :3]
        header = laspy.LasHeader(point_format=0, version="1.2")
        header.scales = np.array([0.001, 0.001, 0.001])
        header.offsets = np.zeros(3)
        las = laspy.LasData(header)
        las.x, las.y, las.z = sensor[:, 0], sensor[:, 1], sensor[:, 2]
        name = f"street_scan{i}.laz"
        las.write(OUT / name)
        entries.append({"file": name, "pose": np.asarray(pose).tolist(), "origin": pose[:3, 3].tolist()})
    (OUT / "poses.json").write_text(json.dumps({"scans": entries, "region": list(sim.region.as_tuple()),
                                                "seed": SEED, "style": sim.scene.style}, indent=1))
    print("wrote", sorted(p.name for p in OUT.iterdir()))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Files of one simulated scene for people and other tools: scans as PLY in the sensor frame with a poses
JSON (the CONTRACTS.md layout `hgca complete --poses` reads), the ground-truth mesh, the sample, a preview."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import trimesh

from hgca_core.dataset.samples import save_sample
from hgca_core.io import write_mesh, write_points
from hgca_core.io.atomic import atomic_write
from hgca_core.synth.dataset import Simulation


def region_mesh(sim: Simulation, pad: float = 0.5) -> trimesh.Trimesh:
    """The scene's faces that reach into the region (padded), in world coordinates, with a per-vertex
    `label` attribute (every vertex belongs to one primitive, so its label is its faces' label)."""
    mesh = sim.scene.mesh
    local = sim.region.to_local(mesh.vertices)
    tri = local[mesh.faces]
    keep = np.all((tri.max(axis=1) >= -pad) & (tri.min(axis=1) <= sim.region.size + pad), axis=1)
    faces = np.asarray(mesh.faces)[keep]
    used, inverse = np.unique(faces, return_inverse=True)
    out = trimesh.Trimesh(mesh.vertices[used], inverse.reshape(-1, 3), process=False)
    vlabel = np.zeros(len(mesh.vertices), dtype=np.uint8)
    vlabel[faces.ravel()] = np.repeat(sim.scene.face_labels[keep], 3)
    out.vertex_attributes["label"] = vlabel[used]
    return out


def write_scene(sim: Simulation, out_dir: str | os.PathLike, preview: bool = True) -> list[str]:
    """Write scene_<seed>.npz, scene_<seed>_scan<i>.ply (sensor frame), scene_<seed>_poses.json,
    scene_<seed>_gt.ply and scene_<seed>_preview.png into out_dir; returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"scene_{sim.scene.seed}"
    paths = [save_sample(out / f"{stem}.npz", sim.sample)]
    entries = []
    for i, (pts, pose) in enumerate(zip(sim.scans_world, sim.poses_world)):
        name = f"{stem}_scan{i}.ply"
        local = (pts - pose[:3, 3]) @ pose[:3, :3]               # world -> sensor (pose is rigid)
        paths.append(write_points(out / name, local))
        entries.append({"file": name, "pose": np.asarray(pose).tolist(), "origin": pose[:3, 3].tolist()})
    doc = {"scans": entries, "region": list(sim.region.as_tuple()), "seed": sim.scene.seed, "style": sim.scene.style}
    lines = ",\n  ".join(json.dumps(e) for e in entries)  # one scan per line: readable, still plain JSON
    rest = json.dumps({k: v for k, v in doc.items() if k != "scans"})[1:-1]
    payload = f'{{"scans": [\n  {lines}\n ],\n {rest}}}\n'.encode()
    paths.append(atomic_write(out / f"{stem}_poses.json", lambda f: f.write(payload)))
    paths.append(write_mesh(out / f"{stem}_gt.ply", region_mesh(sim)))
    if preview:
        from hgca_core.synth.preview import render_preview

        paths.append(render_preview(sim.sample, out / f"{stem}_preview.png"))
    return [os.fspath(p) for p in paths]

"""One completion, end to end: points in the world frame -> k meshes in the world frame.

This is the Python API behind `hgca complete` (and `hgca_core.complete`). Data flow as in DESIGN.md:
region -> crop -> voxelise -> coarse GCA (+ planner) -> [fine cGCA -> unsigned distance -> marching cubes]
-> mesh back in the input's frame with each vertex's distance to the nearest input point.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from hgca_core.errors import InputError
from hgca_core.geometry import coords as cs
from hgca_core.geometry.region import Region
from hgca_core.geometry.voxel import COARSE, FINE, voxelize_coarse

ProgressFn = Callable[[str, int, int, str], None]
# Peak memory of a full-stage completion, linear in the region's area: benchmarks/results/completion_full_cpu
# measured 2.90 GiB at 40 x 40 m and 5.31 GiB at 40 x 120 m (0.81 MB per m^2 on top of ~1.7 GiB). With margin,
# used to refuse regions that cannot fit before spending minutes on them.
BASE_BYTES = 2.0 * 2**30
BYTES_PER_M2 = 1.5e6


@dataclass
class Completion:
    """One sample: the mesh (world frame), per-vertex distance to the input, and the coarse cells."""

    mesh: trimesh.Trimesh
    observed_distance: np.ndarray
    coarse_cells: np.ndarray  # (M, 3) int, 20 cm cells in the region frame
    region: Region
    seed: int

    @property
    def vertices(self) -> np.ndarray:
        """(V, 3) float64 vertex positions, world frame."""
        return np.asarray(self.mesh.vertices)

    @property
    def faces(self) -> np.ndarray:
        """(F, 3) int64 triangle vertex indices."""
        return np.asarray(self.mesh.faces)


def default_weights(stage: str) -> Path:
    from hgca_core.models.checkpoint import WEIGHTS_DIR

    return WEIGHTS_DIR / f"{stage}.pt"


def check_points(points: np.ndarray, what: str = "input") -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"{what}: points must be an (N, 3) array, got shape {p.shape}")
    if len(p) == 0:
        raise InputError(f"{what}: there are no points")
    if not np.all(np.isfinite(p)):
        raise InputError(f"{what}: {int((~np.isfinite(p)).any(1).sum())} points have NaN or infinite coordinates")
    return p


def check_memory(region: Region) -> None:
    """Refuse a region whose estimated peak memory exceeds what this machine has available."""
    import psutil

    need = BASE_BYTES + float(region.size[0] * region.size[1]) * BYTES_PER_M2
    avail = psutil.virtual_memory().available
    if need > avail:
        raise InputError(f"region {region.size[0]:.1f} x {region.size[1]:.1f} m needs about {need / 2**30:.1f} GiB, "
                         f"only {avail / 2**30:.1f} GiB available: use a smaller --region or split it into tiles")


def complete(points: np.ndarray, region: Region | None = None, origins: np.ndarray | None = None,
             samples: int = 1, seed: int = 0, stage: str = "coarse", device: str = "cpu",
             t1: int | None = None, t2: int | None = None, weights: str | Path | None = None,
             fine_weights: str | Path | None = None, progress: ProgressFn | None = None,
             precision: str = "auto", max_faces: int | None = None) -> list[Completion]:
    """Complete accumulated LiDAR points. Sample i uses seed + i, so a (seed, i) pair names one mesh.

    `precision` is the GEMM precision of the sparse convs while sampling ('auto': bf16 where the hardware has
    it, see `hgca_core.nn.conv.resolve_precision`); a (seed, precision) pair names one result. `max_faces`
    simplifies each mesh to at most that many triangles (`hgca_core.meshing.decimate`; None: the default of
    `hgca_core.meshing.DEFAULT_MAX_FACES`, 0: keep every triangle). Each mesh carries per-vertex normals and
    `observed_distance` and an observed / generated face `material` (`hgca_core.meshing.finish_mesh`)."""
    if stage not in ("coarse", "full"):
        raise InputError(f"stage must be 'coarse' or 'full', not {stage!r}")
    fine_path = Path(fine_weights or default_weights("fine"))
    if stage == "full" and not fine_path.exists():
        raise InputError("no fine-stage weights (train them with `hgca train fine`, or pass --fine-weights); "
                         "use --stage coarse", str(fine_path))
    if samples < 1:
        raise InputError(f"samples must be at least 1, got {samples}")
    if max_faces is not None and max_faces != 0 and max_faces < 1000:
        raise InputError(f"max_faces must be 0 (keep every triangle) or at least 1000, got {max_faces}")
    pts = check_points(points)
    if region is None:
        sensor = None if origins is None or len(origins) == 0 else np.asarray(origins)[0]
        region = Region.around(pts, sensor=sensor)
    check_memory(region)
    report = progress or (lambda *a: None)
    local = region.to_local(pts)
    inside = region.contains_local(local)
    if not inside.any():
        raise InputError(f"no input points inside the region (centre {np.round(region.center, 2).tolist()}, "
                         f"size {region.size.tolist()} m); the points span {np.round(pts.min(0), 2).tolist()} "
                         f"to {np.round(pts.max(0), 2).tolist()}")
    s0 = voxelize_coarse(local[inside], region.grid_shape(FINE))
    grid = region.grid_shape(COARSE)
    report("voxelise", 1, 1, f"{len(s0)} cells at 20 cm")

    from hgca_core.models.checkpoint import load_coarse
    from hgca_core.models.gca import sample as gca_sample
    from hgca_core.nn.conv import gemm_precision, resolve_precision

    model, _ = load_coarse(str(weights or default_weights("coarse")), device)
    try:
        gemm_dtype = resolve_precision(precision, device)
    except ValueError as exc:
        raise InputError(str(exc)) from exc
    steps = t1 or model.cfg.steps
    tree = cKDTree(pts[inside])
    # sensor positions (region frame) that observed faces turn towards; without them one 2 m above the
    # ground at the region's centre (the region's box starts 1 m below the ground)
    sensors = (region.to_local(np.asarray(origins, dtype=np.float64).reshape(-1, 3))
               if origins is not None and len(origins) else np.array([[*(region.size[:2] / 2), 3.0]]))
    results = []
    for i in range(samples):
        gen = torch.Generator(device=device).manual_seed(seed + i)
        s0_t = cs.with_batch(torch.from_numpy(s0).to(device))
        with gemm_precision(gemm_dtype):
            occ = gca_sample(model, s0_t, grid, steps, gen,
                             lambda t, n: report("planner" if t == 0 else "coarse", t, n, f"sample {i + 1}/{samples}"))
        cells = occ[:, 1:].cpu().numpy()
        if stage == "full":
            from hgca_core.models.cgca import decode_mesh, load_fine, upsample

            fine_model, autoencoder, _ = load_fine(str(fine_path), device)
            with gemm_precision(gemm_dtype):
                cells10, latents = upsample(fine_model, autoencoder, local[inside], cells, region.grid_shape(FINE), t2,
                                            gen, lambda t, n: report("fine", t, n, f"sample {i + 1}/{samples}"))
            report("mesh", i, samples, f"sample {i + 1}/{samples}")
            mesh = decode_mesh(autoencoder, cells10, latents, points=local[inside], sensors=sensors)
        else:
            from hgca_core.meshing import voxel_mesh

            report("mesh", i, samples, f"sample {i + 1}/{samples}")
            mesh = voxel_mesh(cells, COARSE, lower_corner=-FINE / 2)
        from hgca_core.meshing import DEFAULT_MAX_FACES, decimate, finish_mesh

        limit = DEFAULT_MAX_FACES if max_faces is None else max_faces
        if limit and len(mesh.faces) > limit:
            report("mesh", i, samples, f"sample {i + 1}/{samples}: simplifying {len(mesh.faces)} faces")
            mesh = decimate(mesh, limit)
        mesh.vertices = region.to_world(mesh.vertices)
        dist = tree.query(mesh.vertices, workers=-1)[0].astype(np.float32) if len(mesh.vertices) else np.zeros(0, np.float32)
        mesh = finish_mesh(mesh, dist)
        results.append(Completion(mesh=mesh, observed_distance=dist, coarse_cells=cells, region=region, seed=seed + i))
        report("mesh", i + 1, samples, f"sample {i + 1}/{samples}")
    return results

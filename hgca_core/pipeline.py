"""One completion, end to end: points in the world frame -> k meshes in the world frame.

Two layers, so that `hgca eval` scores exactly what `hgca complete` ships:
- `complete_local`, the region-frame core: points in a region's frame -> k meshes in that frame (crop to the box,
  voxelise, coarse GCA (+ planner), [fine cGCA -> unsigned distance -> marching cubes] or the coarse cells'
  blocky mesh). No file I/O, no world coordinates; `hgca eval` calls it on the synthetic samples, which are
  stored in their region frame.
- `complete`, the world-frame wrapper behind `hgca complete` and `hgca_core.complete`: checks the input, picks the
  region, moves points into its frame, loads the weights, runs the core and moves each mesh back, with each
  vertex's distance to the nearest input point. World-frame concerns (frames, offsets) live here only.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np
import torch
import trimesh

from hgca_core.config import STAGES, CompletionConfig, check_device_name
from hgca_core.errors import HgcaWarning, InputError
from hgca_core.geometry import coords as cs
from hgca_core.geometry.nearest import PointIndex
from hgca_core.geometry.points import check_points
from hgca_core.geometry.region import Region, default_region
from hgca_core.geometry.voxel import COARSE, FINE, voxelize
from hgca_core.hardware import release_free_memory
from hgca_core.meshing.decimation import limit_faces
from hgca_core.meshing.finish import observed_distances
from hgca_core.meshing.voxel_mesh import voxel_mesh

if TYPE_CHECKING:
    from hgca_core.models.autoencoder import Autoencoder
    from hgca_core.models.cgca import CGCAKernel
    from hgca_core.models.gca import GCAKernel

ProgressFn = Callable[[str, int, int, str, int], None]  # (stage, step, total, message, sample index)
DEFAULTS = CompletionConfig()   # every setting's default (`hgca_core.config`)
# Observed free space (`--free-space`, `config.FREE_SPACE_MODES`): feature = the input of the networks trained with
# it; mask = that input where taken, and the free space's core (seen-empty cells whose six neighbours are seen empty
# too, `geometry.freespace.confident`) forbidden in every sampled state; auto = mask for weights trained with the
# feature (the shipped ones), nothing for weights without it (their results stay those of before); off = neither
# (networks trained with it see "unknown" everywhere). The core, not the whole free space: grazing rays cross the
# top of ground cells between LiDAR rings, so the free space's rim holds true surface
# (benchmarks/results/freespace_floor.md in git at 7f06b18); forbidding the core changed no val score (62.02 -> 62.03 % IoU).
# Peak memory of a full-stage completion, linear in the region's area: benchmarks/results/completion_full_cpu
# measured 2.90 GiB at 40 x 40 m and 5.31 GiB at 40 x 120 m (0.81 MB per m^2 on top of ~1.7 GiB). With margin,
# used to refuse regions that cannot fit before spending minutes on them.
BASE_BYTES = 2.0 * 2**30
BYTES_PER_M2 = 1.5e6
MEASURED_HEIGHT = 8.0   # metres: the height of the regions the slope was measured on
# Fewer occupied 20 cm cells than this inside the region is no scan (one point, one spot measured 50k times):
# the chain has nothing to grow from, and an empty mesh with exit 0 would look like success.
MIN_INPUT_CELLS = 10


def check_device(device: str) -> None:
    """Refuse a device this torch build or machine does not have, before any work (the name's form is checked by
    `config.check_device_name`)."""
    check_device_name(device)
    if not device.startswith("cuda"):
        return
    if not torch.cuda.is_available():
        raise InputError(f"--device {device} asked for, but this torch build sees no CUDA GPU; use --device cpu")
    index = int(device.split(":")[1]) if ":" in device else 0
    if index >= torch.cuda.device_count():
        raise InputError(f"--device {device}: this machine has {torch.cuda.device_count()} CUDA GPU(s)")


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


@dataclass
class LocalCompletion:
    """One sample in the region frame, as the core computes it."""

    mesh: trimesh.Trimesh              # region frame
    coarse_cells: np.ndarray           # (M, 3) int64, 20 cm cells (s^T1)
    fine_cells: np.ndarray | None      # (N, 3) int64, 10 cm cells (x^T2) of the full stage, else None
    seed: int
    free_cells: int | None = None      # 20 cm cells seen empty that the run used (None: no free space)
    fine_latents: np.ndarray | None = None   # (N, K) float32 latents of fine_cells (row-aligned), else None
    observed_distance: np.ndarray | None = None   # (V,) float32: each mesh vertex's distance to the input (m)


@dataclass
class Models:
    """The networks a completion runs: the coarse kernel, and for the full stage the fine kernel with the
    autoencoder it was trained with."""

    coarse: "GCAKernel"
    fine: "CGCAKernel | None" = None
    autoencoder: "Autoencoder | None" = None


def memory_need(region: Region) -> float:
    """Estimated peak bytes of one completion of `region` (the measured slope above, with margin); `check_memory`
    refuses by it and `hgca drive` declares it as each tile's Ray memory. The slope was measured on 8 m tall
    regions; a taller box holds proportionally more cells (the free-space grid is dense), so it scales with the
    height beyond 8 m."""
    tall = max(1.0, float(region.size[2]) / MEASURED_HEIGHT)
    return BASE_BYTES + float(region.size[0] * region.size[1]) * BYTES_PER_M2 * tall


def check_input_cells(cells: int, points: np.ndarray) -> None:
    """Refuse inputs too small or degenerate to complete, before any sampling."""
    if cells >= MIN_INPUT_CELLS:
        return
    same = ", all at the same spot," if len(points) > 1 and len(np.unique(points, axis=0)) == 1 else ""
    raise InputError(f"too few input points to complete: {len(points)} point(s) inside the region{same} occupy "
                     f"{cells} cell(s) of 20 cm; at least {MIN_INPUT_CELLS} are needed")


def check_memory(region: Region) -> None:
    """Refuse a region whose estimated peak memory exceeds what this machine has available."""
    import psutil

    need = memory_need(region)
    avail = psutil.virtual_memory().available
    if need > avail:
        raise InputError(f"region {region.size[0]:.1f} x {region.size[1]:.1f} x {region.size[2]:.1f} m needs about "
                         f"{need / 2**30:,.1f} GiB, "
                         f"only {avail / 2**30:.1f} GiB available: use a smaller --region or split it into tiles")


def load_models(stage: str, weights: str | Path | None = None, fine_weights: str | Path | None = None,
                device: str = "cpu") -> Models:
    """The networks `stage` needs ('coarse' or 'full'), from the given files or the shipped ones (None), through
    `hgca_core.models.weights` (checked and cached per file and device)."""
    from hgca_core.models.weights import load_coarse, load_fine

    if stage not in STAGES:
        raise InputError(f"stage must be one of {', '.join(STAGES)}, not {stage!r}")
    models = Models(load_coarse(weights, device)[0])
    if stage == "full":
        models.fine, models.autoencoder, _ = load_fine(fine_weights, device)
    return models


def takes_free_space(models: Models) -> bool:
    """Whether any of the loaded networks was trained with observed free space as an input."""
    return any(m is not None and getattr(m.cfg, "free_space", False) for m in (models.coarse, models.fine))


def observed_free(local: np.ndarray, region: Region, models: Models, mode: str, origins: np.ndarray | None,
                  origin_index: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    """(seen-empty 20 cm cells as a dense (X, Y, Z) bool grid or None, the cells to forbid or None, a note for the
    progress line) for `mode` (one of FREE_SPACE_MODES, checked by `CompletionConfig`). Asked for explicitly
    (feature, mask) without sensor origins, or as a feature the weights do not take, it is an `InputError`; auto
    without origins gives None and, when the weights take the feature, a warning that it is all unknown."""
    from hgca_core.geometry.freespace import confident, observed_empty

    takes = takes_free_space(models)
    if mode == "off" or (mode == "auto" and not takes):
        return None, None, "off" if mode == "off" else "not an input of these weights"
    if mode == "feature" and not takes:
        raise InputError("--free-space feature: these weights were trained without observed free space as an "
                         "input (use --free-space mask to forbid the core of the seen-empty space, or weights "
                         "trained with `hgca train --free-space`)")
    if origins is None or len(origins) == 0:
        if mode != "auto":
            raise InputError(f"--free-space {mode} needs the sensor origins of the scans (poses or origins in "
                             "the files), and these points have none")
        if takes:
            warnings.warn(HgcaWarning("no sensor origins: observed free space is unknown, so the weights' free-space "
                                      "input is all 'unknown' and nothing is masked"), stacklevel=3)
        return None, None, "unknown (no sensor origins)"
    free = observed_empty(local, origins, origin_index, region.grid_shape(COARSE))
    forbid = confident(free) if mode in ("mask", "auto") else None    # auto gets here for free-space weights
    note = "input" if takes else ""
    if forbid is not None:
        note += f"{' + ' if note else ''}mask of its core ({int(forbid.sum())} cells)"
    return free, forbid, f"{note}: {int(free.sum())} cells"


def _initial_states(observed: np.ndarray, fixed_cells: np.ndarray | Sequence[np.ndarray] | None, samples: int,
                    grid: tuple[int, int, int]) -> list[np.ndarray]:
    """Each sample's s0: the input's cells with its fixed cells (one array for every sample, or one per sample)
    inside the grid."""
    from hgca_core.geometry.keys import unique_rows

    if fixed_cells is None:
        return [observed] * samples
    per_sample = list(fixed_cells) if isinstance(fixed_cells, (list, tuple)) else [fixed_cells] * samples
    if len(per_sample) != samples:
        raise ValueError(f"fixed_cells gives {len(per_sample)} samples' cells for {samples} samples")
    starts = []
    for cells in per_sample:
        fixed = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
        fixed = fixed[np.all((fixed >= 0) & (fixed < np.asarray(grid)), axis=1)]
        starts.append(unique_rows(np.concatenate([observed, fixed])) if len(fixed) else observed)
    return starts


def complete_local(local: np.ndarray, region: Region, models: Models, config: CompletionConfig | None = None, *,
                   progress: ProgressFn | None = None, origins: np.ndarray | None = None,
                   origin_index: np.ndarray | None = None,
                   fixed_cells: np.ndarray | Sequence[np.ndarray] | None = None, **settings) -> list[LocalCompletion]:
    """The region-frame core: `local` (N, 3) points in `region`'s frame (metres; only the region's size is used
    here) -> `config.samples` completions, meshes in the same frame, as `config` says (default: its defaults;
    `settings` change single fields, as in `complete`; its bounds were checked when it was made). Sample i uses
    seed + i. The models must be those `load_models(config.stage, ...)` gives.

    Points outside the box [0, size) are dropped first, so every caller crops the same way; the observed free
    space uses every point's ray (a ray to a hit outside the box still crosses it). `origins` (S, 3) are the
    sensor positions in the region frame and `origin_index` (N,) each point's (None: the nearest origin, see
    `geometry.freespace.ray_origins`); `config.free_space` says what the free space does. It is computed
    once and given to both stages. The coarse stage's mesh is the 20 cm cells' `voxel_mesh`; the full stage's
    is the zero level of the decoded unsigned distance as one surface, its observed parts facing `origins`
    (`hgca_core.meshing.fine.udf_mesh`). Runs on the models' device; `config.device` is where they were loaded.

    `fixed_cells` ((M, 3) 20 cm cells in this frame) join the initial state s0 exactly as observed cells do:
    `hgca drive` passes the cells its finished neighbours generated in a tile's overlap, so the joins agree.
    A list of such arrays gives each sample its own (a drive tile's sample k joins its neighbours' sample k), so
    the free space and the input's cells are computed once for all samples. Cells outside the grid are ignored;
    None (or none inside) leaves the run unchanged.
    """
    from hgca_core.models.gca import sample as gca_sample
    from hgca_core.nn.conv import gemm_precision, resolve_precision
    from hgca_core.nn.sparse import CellState

    cfg = (config or DEFAULTS).with_(**settings)
    stage, t2 = cfg.stage, cfg.t2
    if stage == "full" and (models.fine is None or models.autoencoder is None):
        raise InputError("the full stage needs the fine kernel and its autoencoder (load_models('full', ...))")
    device = next(models.coarse.parameters()).device
    try:
        gemm_dtype = resolve_precision(cfg.precision, str(device))
    except ValueError as exc:
        raise InputError(str(exc)) from exc
    report = progress or (lambda *a: None)
    everything = np.asarray(local, dtype=np.float64).reshape(-1, 3)
    inside = region.contains_local(everything)
    local = everything[inside]
    if len(local) == 0:
        raise InputError(f"no input points inside the {region.size.tolist()} m region")
    if origins is not None and len(origins) and origin_index is None:
        from hgca_core.geometry.freespace import ray_origins

        origin_index = ray_origins(np.asarray(origins), {}, everything)
    free_np, forbid_np, note = observed_free(everything, region, models, cfg.free_space, origins, origin_index)
    free = None if free_np is None else torch.from_numpy(free_np)[None].to(device)
    forbid = None if forbid_np is None else torch.from_numpy(forbid_np)[None].to(device)
    report("free space", 1, 1, note, 0)
    observed = voxelize(local, COARSE, region.size)
    grid = region.grid_shape(COARSE)
    check_input_cells(len(observed), local)
    starts = _initial_states(observed, fixed_cells, cfg.samples, grid)
    report("voxelise", 1, 1, f"{len(starts[0])} cells at 20 cm", 0)
    steps = cfg.t1 or models.coarse.cfg.steps
    # where observed faces of the full stage's surface turn to; without origins a sensor 2 m above the ground
    # at the region's centre (the box starts 1 m below the ground)
    sensors = (np.asarray(origins, dtype=np.float64).reshape(-1, 3) if origins is not None and len(origins)
               else np.array([[*(np.asarray(region.size[:2]) / 2), 3.0]]))
    tree = PointIndex(local)  # the input points, for the fairing's anchors and each vertex's observed_distance
    results = []
    samples, seed = cfg.samples, cfg.seed
    for i in range(samples):
        tag, s0 = f"sample {i + 1}/{samples}", starts[i]
        gen = torch.Generator().manual_seed(seed + i)   # on the CPU on any device: one seed, one mesh
        with gemm_precision(gemm_dtype):
            start = CellState(cs.with_batch(torch.from_numpy(s0).to(device)), grid)
            occ = gca_sample(models.coarse, start, steps, gen,
                             lambda t, n: report("planner" if t == 0 else "coarse", t, n, tag, i), free, forbid)
        cells, cells10, latents10 = occ[:, 1:].cpu().numpy(), None, None
        if stage == "full":
            from hgca_core.meshing.fine import udf_mesh
            from hgca_core.models.cgca import upsample

            release_free_memory()   # the coarse chain's holes in the heap, before the fine stage's larger maps
            with gemm_precision(gemm_dtype):
                c10, latents = upsample(models.fine, models.autoencoder, local, cells, region.grid_shape(FINE), t2,
                                        gen, lambda t, n: report("fine", t, n, tag, i), free, forbid)
            report("mesh", 0, 1, tag, i)
            release_free_memory()   # and the fine stage's, before meshing
            mesh = udf_mesh(models.autoencoder, c10, latents, voxel=models.autoencoder.cfg.voxel, points=local,
                            sensors=sensors, tree=tree)
            cells10, latents10 = c10.cpu().numpy(), latents.float().cpu().numpy()
        elif stage == "preview":
            from hgca_core.meshing.voxel_mesh import smooth_cells_mesh

            report("mesh", 0, 1, tag, i)
            mesh = smooth_cells_mesh(cells, COARSE, grid)
        else:
            report("mesh", 0, 1, tag, i)
            mesh = voxel_mesh(cells, COARSE)
        mesh = limit_faces(mesh, cfg.max_faces, lambda note: report("mesh", 0, 1, f"{tag}: {note}", i))
        if len(mesh.faces) == 0:  # inputs too small to complete were refused above: this is the model's doing
            warnings.warn(HgcaWarning(f"{tag} is an empty mesh: the model made no surface from {len(s0)} input "
                                      "cells (untrained or mismatched weights?)"), stacklevel=2)
        dist = observed_distances(mesh.vertices, tree)
        results.append(LocalCompletion(mesh=mesh, coarse_cells=cells, fine_cells=cells10, seed=seed + i,
                                       free_cells=None if free_np is None else int(free_np.sum()),
                                       fine_latents=latents10, observed_distance=dist))
        report("mesh", 1, 1, tag, i)
    return results


def complete(points: np.ndarray, region: Region | None = None, origins: np.ndarray | None = None,
             config: CompletionConfig | None = None, *, progress: ProgressFn | None = None,
             origin_index: np.ndarray | None = None, **settings) -> list[Completion]:
    """Complete accumulated LiDAR points (world frame) as `config` says (`CompletionConfig`, default: its
    defaults); `settings` (any of its fields: stage=, samples=, seed=, t1=, ...) change single ones. Sample i
    uses seed + i, so a (seed, i) pair names one mesh; a (seed, precision) pair names one result.

    `region` None is `geometry.region.default_region` around the first sensor. `origins` (S, 3, world frame) are
    the sensor positions and `origin_index` (N,) names each point's (a reader's `origin_index` / `scan_index`,
    see `geometry.freespace.ray_origins`; None: the nearest origin). With them the observed free space is
    computed and used as `config.free_space` says. Each mesh is simplified to at most `config.max_faces`
    triangles (0: every one) and carries per-vertex normals, `observed_distance` and an observed / generated
    face `material` (`hgca_core.meshing.finish.finish_mesh`). The work itself is `complete_local`'s, in the region
    frame; this wrapper moves points in and meshes out."""
    cfg = (config or DEFAULTS).with_(**settings)
    check_device(cfg.device)
    models = load_models(cfg.stage, cfg.coarse_file(), cfg.fine_file(), cfg.device)   # both checked before work
    head = None
    if cfg.semantics:
        from hgca_core.models.weights import load_semantics

        head = load_semantics(cfg.semantics_weights, cfg.device)
    from hgca_core.meshing.finish import finish_mesh

    pts = check_points(points)
    if region is None:
        region = default_region(pts, origins)
    check_memory(region)
    local = region.to_local(pts)
    inside = region.contains_local(local)
    if not inside.any():
        raise InputError(f"no input points inside the region (centre {np.round(region.center, 2).tolist()}, "
                         f"size {region.size.tolist()} m); the points span {np.round(pts.min(0), 2).tolist()} "
                         f"to {np.round(pts.max(0), 2).tolist()}")
    if origin_index is not None and len(origin_index) != len(pts):
        raise InputError(f"origin_index has {len(origin_index)} entries for {len(pts)} points")
    origins_local = None if origins is None or len(origins) == 0 else region.to_local(np.asarray(origins, np.float64))
    results = []
    for r in complete_local(local, region, models, cfg, progress=progress, origins=origins_local,
                            origin_index=origin_index):
        mesh = r.mesh
        mesh.vertices = region.to_world(mesh.vertices)
        mesh = finish_mesh(mesh, r.observed_distance)
        results.append(Completion(mesh=mesh, observed_distance=r.observed_distance, coarse_cells=r.coarse_cells,
                                  region=region, seed=r.seed))
    if head is not None:   # after the geometry, which it reads and never changes
        from hgca_core.models.semantics import label_completions

        label_completions(head, results, voxelize(local[inside], COARSE, region.size), region.to_local)
    return results

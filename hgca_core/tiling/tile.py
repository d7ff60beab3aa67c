"""One tile's completion as a pure function of its inputs: the unit `hgca drive` runs in-process or as a Ray task.

`complete_tile` takes everything it needs as arguments (the job, the tile's scans as float64 world points, the
neighbours' coarse cells) and returns arrays, touching no file: the driver alone writes results, under the
job's content key, so a retried or duplicated task can never leave two copies or half a file. Each sample is
one `pipeline.complete_local` run (sample k uses the tile's seed + k, as `hgca complete` does) whose initial
state also holds, fixed like the input, the cells the finished neighbours' sample k generated in this tile.
"""
from __future__ import annotations

import hashlib
import json
import os
import socket
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from hgca_core.config import CompletionConfig
from hgca_core.errors import InputError
from hgca_core.geometry.region import Region
from hgca_core.geometry.voxel import COARSE, cell_centers, voxelize
from hgca_core.hardware import peak_rss_bytes
from hgca_core.io.digest import file_digest

KEY_VERSION = 3   # bump when the same key would give different content (a change to this algorithm)


@dataclass(frozen=True)
class Settings:
    """What every tile of a drive is completed with: the drive's completion config (`DriveConfig.completion`) on
    `threads` torch threads. `device` decides only where, not what, so it is not part of a tile's key; nor is
    `threads` at fp32 (MKL's strict mode makes float32 GEMMs thread-count independent). bf16 GEMMs (oneDNN)
    differ between thread counts on some CPUs, so at any other precision the thread count is part of the key: a
    resumed drive never mixes tiles made on 1 and 2 threads. The weights enter the key by digest
    (`TileJob.weights`), not by name or quality."""

    config: CompletionConfig
    threads: int

    def files(self) -> list[Path]:
        """The weights files each tile loads (`weight_files` of the config's stage and quality)."""
        c = self.config
        return weight_files(c.stage, c.coarse_file(), c.fine_file())

    def keyed(self) -> dict:
        """The settings as a tile's key holds them (the same document since key version 3)."""
        c = self.config
        d = {"stage": c.stage, "samples": c.samples, "seed": c.seed, "t1": c.t1, "t2": c.t2,
             "precision": c.precision, "max_faces": c.max_faces or None, "threads": self.threads,
             "free_space": c.free_space}
        if c.precision == "fp32":
            d.pop("threads")
        return d


@dataclass(frozen=True)
class TileJob:
    """Everything that names one tile's result: its region, scans (by content digest), seed, the settings, the
    weights' digests and the keys of the neighbours it is conditioned on. `key` is their hash."""

    index: int
    region: tuple[float, ...]          # Region.as_tuple(): cx, cy, cz, sx, sy, sz, yaw_deg
    scans: tuple[int, ...]
    scan_digests: tuple[str, ...]     # `DriveScan.digest`: points, origins and rays
    seed: int                          # sample k uses seed + k
    settings: Settings
    weights: tuple[str, ...]           # sha256 of the weights files the stage loads
    conditioned_on: tuple[str, ...]    # keys of the finished neighbours whose cells join s0

    @property
    def key(self) -> str:
        doc = {"version": KEY_VERSION, "region": [repr(float(v)) for v in self.region],
               "scans": list(self.scan_digests), "seed": self.seed, "settings": self.settings.keyed(),
               "weights": list(self.weights), "conditioned_on": list(self.conditioned_on)}
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:32]


def weight_files(stage: str, weights: str | None, fine_weights: str | None) -> list[Path]:
    """The files a stage loads: the coarse weights, and for the full stage the fine ones (shipped when None)."""
    from hgca_core.models.weights import shipped

    files = [Path(weights) if weights else shipped("coarse")]
    if stage == "full":
        files.append(Path(fine_weights) if fine_weights else shipped("fine"))
    return files


def transfer_cells(cells: np.ndarray, source: Region, target: Region) -> np.ndarray:
    """20 cm cells of `source`'s frame -> the 20 cm cells of `target`'s frame their centres fall in (only those
    inside `target`'s grid, i.e. in the overlap). One cell each: consecutive tiles' grids differ by a fraction of
    a degree and millimetres of ground height, and mapping a cell's whole box instead thickens every surface by
    a cell wherever the grids are offset (up to a third more cells on a synthetic drive), which the phase-two
    tile then takes as observed."""
    c = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    if len(c) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    return voxelize(target.to_local(source.to_world(cell_centers(c, COARSE))), COARSE, target.size)


def complete_tile(job: TileJob, scans: list, neighbour_cells: list[tuple[tuple, list[np.ndarray]]],
                  progress: Callable | None = None) -> dict:
    """Complete one tile. `scans`: the tile's `inputs.DriveScan`s (float64 world points, origins, rays);
    `neighbour_cells`: (region tuple, [coarse cells of sample k]) of each finished neighbour. Returns the tile's
    result: per sample the mesh in the tile's region frame (float32 vertices: exact to micrometres in a 40 m
    box; the region's float64 `to_world` places them), observed_distance, the coarse cells, the fixed cells it
    was given and the seen-empty cells its free space had (None: no free space)."""
    import torch

    from hgca_core.pipeline import MIN_INPUT_CELLS, complete_local, load_models

    start, started = time.perf_counter(), time.time()
    s, c = job.settings, job.settings.config
    for path, want in zip(s.files(), job.weights):
        if file_digest(path) != want:
            raise InputError(f"weights differ from the driver's (sha256 {file_digest(path)[:12]} here, "
                             f"{want[:12]} there) on {socket.gethostname()}", str(path))
    torch.set_num_threads(max(1, s.threads))
    region = Region.from_tuple(job.region)
    first = np.cumsum([0] + [len(sc.origins) for sc in scans[:-1]])
    everything = region.to_local(np.concatenate([np.asarray(sc.points, dtype=np.float64) for sc in scans]))
    origins = region.to_local(np.concatenate([np.asarray(sc.origins, dtype=np.float64) for sc in scans]))
    rays = np.concatenate([sc.origin_index.astype(np.int64) + f for sc, f in zip(scans, first)])
    local = everything[region.contains_local(everything)]
    models = load_models(c.stage, c.coarse_file(), c.fine_file(), c.device)
    # a tile that sees (almost) nothing gets no mesh, where `hgca complete` would refuse the region
    enough = len(voxelize(local, COARSE, region.size)) >= MIN_INPUT_CELLS
    fixed = []                       # sample k joins its finished neighbours' sample k
    for k in range(c.samples):
        cells_k = [transfer_cells(cells[k], Region.from_tuple(reg), region) for reg, cells in neighbour_cells]
        fixed.append(np.concatenate(cells_k) if cells_k else np.zeros((0, 3), np.int64))
    if not enough:
        samples = [_empty(job.seed + k, len(f)) for k, f in enumerate(fixed)]
    else:
        # every point, not only the box's: a ray to a hit outside the tile still crosses it (complete_local
        # crops); one call for all samples, so the free space and the input's cells are computed once
        done = complete_local(everything, region, models, c.with_(seed=job.seed), progress=progress,
                              origins=origins, origin_index=rays, fixed_cells=fixed)
        samples = [{"vertices": np.asarray(r.mesh.vertices, dtype=np.float32),
                    "faces": np.asarray(r.mesh.faces, dtype=np.int32), "observed_distance": r.observed_distance,
                    "cells": r.coarse_cells.astype(np.int16), "seed": r.seed,
                    "fixed_cells": int(len(np.unique(f, axis=0))), "free_cells": r.free_cells}
                   for r, f in zip(done, fixed)]
    rss = peak_rss_bytes()
    return {"index": job.index, "key": job.key, "samples": samples, "points": int(len(local)),
            "seconds": round(time.perf_counter() - start, 3), "started": started, "finished": time.time(),
            "worker": f"{socket.gethostname()}:{os.getpid()}", "peak_rss": int(rss)}


def _empty(seed: int, fixed: int) -> dict:
    """A tile whose box holds too few input points: no mesh (its neighbours cover what can be covered)."""
    return {"vertices": np.zeros((0, 3), np.float32), "faces": np.zeros((0, 3), np.int32),
            "observed_distance": np.zeros(0, np.float32), "cells": np.zeros((0, 3), np.int16), "seed": seed,
            "fixed_cells": fixed, "free_cells": None}


def cells_of(result: dict) -> list[np.ndarray]:
    """The per-sample coarse cells of a tile result (what a phase-two neighbour is conditioned on)."""
    return [s["cells"] for s in result["samples"]]

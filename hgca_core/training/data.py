"""Training examples from synthetic samples: sparse voxel sets, random crops and flips, and the observed free
space of a sample's input (`free_cells`), cached beside it. The files themselves (full or packed) are read
through `hgca_core.dataset`."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from hgca_core.dataset.packed import is_packed, unpack_cells
from hgca_core.dataset.samples import load_arrays
from hgca_core.errors import InputError
from hgca_core.geometry.freespace import observed_empty
from hgca_core.geometry.keys import pack, unique_rows
from hgca_core.geometry.voxel import COARSE, FINE, grid_shape, point_cells, voxelize
from hgca_core.io.atomic import atomic_write
from hgca_core.synth.rays import input_rays


def grids(path: str | Path) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
    """(10 cm grid, 20 cm grid) of a sample's region, from its stored size."""
    size = load_arrays(str(path), ("region",))["region"][3:6]
    return grid_shape(size, FINE), grid_shape(size, COARSE)


def packed_cells(path: str | Path, name: str) -> np.ndarray:
    """One cell set ("s0", "gt", "free", "visible20") of a packed coarse sample (`dataset.packed`)."""
    a = load_arrays(str(path), ("grid", name))
    return unpack_cells(a[name], a["grid"])


def coarse_pair(path: str | Path) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int]]:
    """(s0, gt, grid) at 20 cm for a sample: the input voxelised as the paper says, and the ground truth."""
    if is_packed(path):
        return packed_cells(path, "s0"), packed_cells(path, "gt"), grids(path)[1]
    a = load_arrays(str(path), ("region", "input_points", "gt_occ20"))
    return voxelize(a["input_points"], COARSE, a["region"][3:6]), a["gt_occ20"].astype(np.int64), grids(path)[1]


def free_path(path: str | Path) -> Path:
    """The observed-free-space sidecar of a sample: sample_X.npz -> sample_X.free20.npy."""
    p = Path(path)
    return p.with_name(p.name.removesuffix(".npz") + ".free20.npy")


def free_cells(path: str | Path) -> np.ndarray:
    """(F, 3) int64 20 cm cells of a sample's region that its input rays saw empty (`observed_empty` of the stored
    input points, beyond the region too from format 3 on (`synth.rays.input_rays`), origins and scan index), sorted.

    Computing it costs 1.5-1.9 s of CPU on a 5-scan sample of 540-700 k points (reading them and the ray walk,
    which alone takes 0.8-1.0 s), and a trainer draws samples at random from the whole split, so the result is kept in a
    sidecar file (the dense grid as packed bits, 184 kB for the default region) written atomically beside the
    sample and read back in 6-50 ms on the busy 2-core machine; a sidecar older than its sample, of the wrong
    size or unreadable is recomputed, and a folder that cannot be written to only costs the recomputation. Not
    kept in memory: reading the sidecar is cheaper than holding a split's worth of cells. A packed sample holds them."""
    if is_packed(path):
        return packed_cells(path, "free")
    shape = grids(path)[1]
    side, n = free_path(path), int(np.prod(shape))
    try:
        if side.stat().st_mtime_ns >= Path(path).stat().st_mtime_ns:
            bits = np.load(side, allow_pickle=False)
            if bits.dtype == np.uint8 and bits.shape == ((n + 7) // 8,):
                return unpack_cells(bits, shape)
    except (OSError, ValueError):
        pass
    with np.load(path, allow_pickle=False) as a:
        points, index = input_rays(a)
        grid = observed_empty(points, a["input_origins"], index, shape)
    try:
        atomic_write(side, lambda f: np.save(f, np.packbits(grid.reshape(-1))))
    except InputError:
        pass   # a read-only dataset: recompute next time
    return np.argwhere(grid).astype(np.int64)


def visible_cells(path: str | Path) -> np.ndarray:
    """(V, 3) int64 20 cm cells the evaluation LiDAR sees (what the IoU scores), of a full or packed sample."""
    if is_packed(path):
        return packed_cells(path, "visible20")
    return load_arrays(str(path), ("visible20",))["visible20"].astype(np.int64)


@dataclass(frozen=True)
class CropSpec:
    """An x/y window [ox, ox + size) x [oy, oy + size) of a grid's cells, then optional flips of x and y.

    One crop for both stages: `cells` works on any grid (20 cm coarse, 10 cm fine); `points` on 10 cm cells."""

    ox: int
    oy: int
    fx: bool
    fy: bool
    grid: tuple[int, int, int]

    def cells(self, c: np.ndarray) -> np.ndarray:
        c = np.asarray(c, dtype=np.int64).reshape(-1, 3) - np.array([self.ox, self.oy, 0])
        c = c[(c[:, 0] >= 0) & (c[:, 0] < self.grid[0]) & (c[:, 1] >= 0) & (c[:, 1] < self.grid[1])]
        if self.fx:
            c[:, 0] = self.grid[0] - 1 - c[:, 0]
        if self.fy:
            c[:, 1] = self.grid[1] - 1 - c[:, 1]
        return unique_rows(c)

    def points(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(points in the crop frame, mask of the kept input rows): a point is kept when its 10 cm cell is,
        and a flip maps cell c to size - 1 - c, i.e. x to (size - 1) * 0.1 - x."""
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3) - np.array([self.ox, self.oy, 0]) * FINE
        c = point_cells(p, FINE)
        keep = (c[:, 0] >= 0) & (c[:, 0] < self.grid[0]) & (c[:, 1] >= 0) & (c[:, 1] < self.grid[1])
        p = p[keep]
        if self.fx:
            p[:, 0] = (self.grid[0] - 1) * FINE - p[:, 0]
        if self.fy:
            p[:, 1] = (self.grid[1] - 1) * FINE - p[:, 1]
        return p.astype(np.float32), keep


FOCUS_HEIGHT = 15  # cells (3 m at 20 cm) above a column's lowest true cell: facades up high and tree crowns


def focus_cells(s0: np.ndarray, gt: np.ndarray, height: int = FOCUS_HEIGHT) -> np.ndarray:
    """True cells the input misses that lie `height` cells or more above the lowest true cell of their x/y
    column: where a street scan is blind (above the scanner's field of view, the crowns) and where the model
    under-extrapolates real scans most, so crops drawn around them put the loss where the error is."""
    gt = np.asarray(gt, dtype=np.int64).reshape(-1, 3)
    if not len(gt):
        return gt
    missing = gt[~np.isin(pack(gt), pack(np.asarray(s0, dtype=np.int64).reshape(-1, 3)))]
    cols, inv = np.unique(gt[:, :2], axis=0, return_inverse=True)
    low = np.full(len(cols), np.iinfo(np.int64).max)
    np.minimum.at(low, inv.reshape(-1), gt[:, 2])
    at = np.searchsorted(pack(np.c_[cols, np.zeros(len(cols), np.int64)]),
                         pack(np.c_[missing[:, :2], np.zeros(len(missing), np.int64)]))
    return missing[missing[:, 2] >= low[at] + height]


def turn_cells(sets: Sequence[np.ndarray], grid: tuple[int, int, int], yaw: float) -> list[np.ndarray]:
    """Every cell set turned by `yaw` (radians) about z through the centre of the grid's x/y extent, where a
    sample's sensor stands, as a region placed at that angle would hold the same street: each target column takes
    the column its centre comes from (inverse nearest-neighbour mapping of the dense grid, so a one-cell wall stays
    one connected cell thick at any angle); columns that come from outside the grid are empty.

    Why: a synthetic region has its x axis along the drive, so without turning the model only sees streets along
    x, while real scans arrive in any frame (the Argoverse 2 city frame, the nuScenes sensor frame's y forward),
    and on them it grows walls along the grid axes, not along the street."""
    from hgca_core.geometry.freespace import dense

    x, y = np.meshgrid(np.arange(grid[0]) + 0.5, np.arange(grid[1]) + 0.5, indexing="ij")
    cx, cy = grid[0] / 2.0, grid[1] / 2.0
    c, s = np.cos(yaw), np.sin(yaw)
    sx = np.floor(c * (x - cx) + s * (y - cy) + cx).astype(np.int64)      # R(-yaw) of the target centre
    sy = np.floor(-s * (x - cx) + c * (y - cy) + cy).astype(np.int64)
    ok = (sx >= 0) & (sx < grid[0]) & (sy >= 0) & (sy < grid[1])
    tx, ty, sx, sy = x[ok].astype(np.int64), y[ok].astype(np.int64), sx[ok], sy[ok]
    out = []
    for cells in sets:
        src = dense(cells, grid)
        turned = np.zeros(tuple(grid), dtype=bool)
        turned[tx, ty] = src[sx, sy]
        out.append(np.argwhere(turned).astype(np.int64))
    return out


def draw_crop(grid: tuple[int, int, int], crop: int | None, rng: np.random.Generator,
              focus: np.ndarray | None = None, focus_share: float = 0.0) -> CropSpec:
    """A random crop (the whole grid when crop is None or too large) and random flips.

    With `focus` cells and probability `focus_share`, the crop is drawn among those that contain a focus cell
    picked at random (uniform offset around it), otherwise uniformly over the grid."""
    if crop is None or crop >= min(grid[0], grid[1]):
        ox = oy = 0
        out = grid
    else:
        if focus is not None and len(focus) and rng.random() < focus_share:
            c = focus[int(rng.integers(len(focus)))]
            ox, oy = (int(np.clip(c[i] - rng.integers(0, crop), 0, grid[i] - crop)) for i in (0, 1))
        else:
            ox, oy = (int(rng.integers(0, g - crop + 1)) for g in grid[:2])
        out = (crop, crop, grid[2])
    return CropSpec(ox, oy, bool(rng.random() < 0.5), bool(rng.random() < 0.5), out)


def crop_flip(sets: list[np.ndarray], grid: tuple[int, int, int], crop: int | None,
              rng: np.random.Generator, focus: np.ndarray | None = None,
              focus_share: float = 0.0) -> tuple[list[torch.Tensor], tuple[int, int, int]]:
    """Cut the same random x/y window from every cell set and flip it at random; returns tensors and the grid."""
    spec = draw_crop(grid, crop, rng, focus, focus_share)
    return [torch.from_numpy(spec.cells(s)) for s in sets], spec.grid

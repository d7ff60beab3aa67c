"""The fine stage's implicit field on the meshing grid: the decoder's unsigned distance evaluated on a 5 cm grid
around the occupied 10 cm cells (`udf_grid`), which `hgca_core.meshing.fine.udf_mesh` turns into a surface, and
the grid points near its zero level (`udf_surface_points`), which training's validation scores as samples.
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from hgca_core.geometry.keys import pack, unpack

# ---------------------------------------------------------------------------------------------------------------
# Unsigned distance -> mesh (the fine stage, paper App. "Other Implementation Details")
#
# Frames: the decoder works in the *cell frame*, where 10 cm cell c has its centre at c * voxel (the region frame,
# since 10 cm cells are made by rounding). The 5 cm evaluation grid has point g at g * res, so with voxel = 2 res a
# cell owns the grid points 2c - 1, 2c, 2c + 1 per axis (its centre, faces, edges and corners). Grid points outside
# every occupied cell are never evaluated: they take the clamp value (one cell), which is what the decoder returns
# there anyway (no occupied cell among their 8 nearest cell centres).
# ---------------------------------------------------------------------------------------------------------------
UdfFn = Callable[[torch.Tensor], torch.Tensor]


def _as_field(decoder: object, cells: torch.Tensor, latents: torch.Tensor | None) -> UdfFn:
    """The query function: `decoder.field(cells, latents)` for an autoencoder, or `decoder` itself when it is
    already a function of region-frame points (metres) -> unsigned distance (metres), e.g. an analytic one."""
    if hasattr(decoder, "field"):
        return decoder.field(cells, latents)  # type: ignore[attr-defined]
    if callable(decoder):
        return decoder  # type: ignore[return-value]
    raise TypeError(f"decoder must have .field(cells, latents) or be callable, got {type(decoder).__name__}")


def _cells_tensor(cells: np.ndarray | torch.Tensor) -> torch.Tensor:
    t = cells.cpu() if isinstance(cells, torch.Tensor) else torch.from_numpy(np.asarray(cells))
    return t.long().reshape(-1, 3)


def _ratio(voxel: float, res: float) -> int:
    r = voxel / res
    if res <= 0 or abs(r - round(r)) > 1e-6 or round(r) < 1:
        raise ValueError(f"voxel ({voxel}) must be a whole multiple of res ({res})")
    return int(round(r))


def udf_grid_points(cells: np.ndarray | torch.Tensor, voxel: float = 0.1, res: float = 0.05) -> np.ndarray:
    """Integer indices (G, 3) of the res-grid points inside or on the boundary of occupied cells, unique, sorted.

    Point g lies at g * res in the cell frame; cell c (centre c * voxel, r = voxel / res) owns the points with
    |g - r c| <= r / 2 on every axis.
    """
    c = (cells.cpu().numpy() if isinstance(cells, torch.Tensor) else np.asarray(cells)).astype(np.int64).reshape(-1, 3)
    if len(c) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    r = _ratio(voxel, res)
    h = r // 2
    o = np.arange(-h, h + 1)
    offs = np.stack(np.meshgrid(o, o, o, indexing="ij"), -1).reshape(-1, 3)
    g = (c[:, None, :] * r + offs[None]).reshape(-1, 3)
    return unpack(np.unique(pack(g)), batched=False)


def udf_grid(decoder: object, cells: np.ndarray | torch.Tensor, latents: torch.Tensor | None = None,
             voxel: float = 0.1, res: float = 0.05, chunk: int = 1 << 15) -> tuple[np.ndarray, np.ndarray]:
    """(grid indices (G, 3) int64, unsigned distances (G,) float32 metres) on the res-grid around occupied cells.

    A decoder with `grid_udf(cells, latents, res, chunk)` (the autoencoder: the same values, evaluated per cell
    without neighbour search) is asked directly; otherwise its query function sees at most `chunk` points at a
    time. Either way memory stays bounded whatever the scene size.
    """
    cells_t = _cells_tensor(cells)
    _ratio(voxel, res)
    if len(cells_t) == 0:
        return np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.float32)
    if hasattr(decoder, "grid_udf") and latents is not None:
        with torch.no_grad():
            g_t, vals_t = decoder.grid_udf(cells_t, latents, res, chunk)  # type: ignore[attr-defined]
        return g_t.cpu().numpy(), vals_t.float().cpu().numpy()
    g = udf_grid_points(cells_t, voxel, res)
    field = _as_field(decoder, cells_t, latents)
    vals = np.empty(len(g), dtype=np.float32)
    with torch.no_grad():
        for a in range(0, len(g), chunk):
            q = torch.from_numpy(g[a:a + chunk].astype(np.float32) * np.float32(res))
            vals[a:a + chunk] = field(q).float().cpu().numpy()
    return g, vals


def project_to_zero(field: UdfFn, points: np.ndarray, steps: int = 1, max_dist: float | None = None,
                    chunk: int = 1 << 16) -> np.ndarray:
    """Move points onto the zero level along the distance gradient: p <- p - d(p) grad d / |grad d|.

    One step is exact for a true distance function; points whose distance is at the clamp (no gradient) or
    above `max_dist` stay where they are.
    """
    p = np.asarray(points, dtype=np.float64).copy()
    for _ in range(max(0, steps)):
        for a in range(0, len(p), chunk):
            q = torch.from_numpy(p[a:a + chunk].astype(np.float32)).requires_grad_(True)
            with torch.enable_grad():
                d = field(q)
                (grad,) = torch.autograd.grad(d.sum(), q)
            n = grad.norm(dim=1, keepdim=True)
            ok = (n[:, 0] > 1e-6) & (d.detach() > 0)
            if max_dist is not None:
                ok &= d.detach() < max_dist
            step = (d.detach()[:, None] * grad / n.clamp(min=1e-6)) * ok[:, None]
            p[a:a + chunk] -= step.double().numpy()
    return p


def udf_surface_points(decoder: object, cells: np.ndarray | torch.Tensor, latents: torch.Tensor | None = None,
                       lower_corner: float | np.ndarray | None = None, voxel: float = 0.1, res: float = 0.05,
                       threshold: float | None = None, chunk: int = 1 << 15, project: int = 0) -> np.ndarray:
    """Grid points "close to the surface": res-grid points with unsigned distance below `threshold` (paper, App.:
    5 cm cells with implicit distance below 0.5, in units of the 10 cm voxel, i.e. 5 cm).

    The default threshold is voxel / 2: res / 2 would miss a plane lying midway between two grid planes (its
    nearest grid points are exactly res / 2 away). With `project` the points are moved onto the zero level,
    which gives surface samples for Chamfer distances rather than the band the paper's IoU uses.
    """
    threshold = 0.5 * voxel if threshold is None else float(threshold)
    shift = np.asarray(-voxel / 2 if lower_corner is None else lower_corner, dtype=np.float64) + voxel / 2
    g, vals = udf_grid(decoder, cells, latents, voxel, res, chunk)
    p = g[vals < threshold].astype(np.float64) * res
    if project and len(p):
        p = project_to_zero(_as_field(decoder, _cells_tensor(cells), latents), p, steps=project, max_dist=voxel * 0.999)
    return p + shift

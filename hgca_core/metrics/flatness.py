"""How flat and how single-layered a mesh's ground is: vertical rays on flat 2 x 2 m patches of road and sidewalk.

Scan-ring ripples and double layers are both about the ground seen from above, so both are measured with
vertical rays: on a regular x/y grid inside each flat patch, a ray from above counts the mesh's surfaces within a
band around the ground (`layers`) and its first hit gives a height sample; a plane fitted per patch then leaves
the RMS height residual (`patch_rms`). The same plane fit on the input points or ground-truth surface samples of
the same patches says how flat the ground can be (sensor noise) and is (the world).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from hgca_core.geometry.planes import Planes, fit_planes

PATCH = 2.0     # metres, patch edge
BAND = 0.15     # metres above / below the ground height that count as "the ground"


@dataclass
class Patches:
    """Flat ground patches: lower corners (P, 2) in x/y, edge `size`, and the ground height (P,) of each."""

    corners: np.ndarray
    height: np.ndarray
    size: float = PATCH

    def index(self, xy: np.ndarray) -> np.ndarray:
        """Patch index of each x/y point, -1 outside every patch."""
        key = np.floor(np.asarray(xy)[:, :2] / self.size).astype(np.int64)
        own = np.floor(self.corners / self.size + 0.5).astype(np.int64)
        ok, pos = _rows_in(key, own)
        return np.where(ok, pos, -1)


def _rows_in(a: np.ndarray, table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(found, position) of each integer row of a (N, 2) in table (P, 2)."""
    ka = a[:, 0] * (1 << 32) + a[:, 1]
    kt = table[:, 0] * (1 << 32) + table[:, 1]
    order = np.argsort(kt)
    i = np.searchsorted(kt[order], ka).clip(max=max(len(kt) - 1, 0))
    if len(kt) == 0:
        return np.zeros(len(a), bool), np.zeros(len(a), np.int64)
    return kt[order][i] == ka, order[i]


def flat_patches_from_labels(surface: np.ndarray, label: np.ndarray, ground_labels: tuple[int, ...] = (0, 1),
                             size: float = PATCH, min_points: int = 200, clearance: float = 0.5) -> Patches:
    """Patches whose ground-truth surface samples within `clearance` of the ground are all of one ground label
    (road or sidewalk: no kerb inside) and nothing else (no car, pole or trunk standing in it)."""
    p = np.asarray(surface, dtype=np.float64)
    lab = np.asarray(label)
    key = np.floor(p[:, :2] / size).astype(np.int64)
    uk, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    is_ground = np.isin(lab, ground_labels)
    gz = np.full(len(uk), np.inf)
    np.minimum.at(gz, inv[is_ground], p[is_ground, 2])
    low = p[:, 2] < gz[inv] + clearance
    n_low = np.bincount(inv, weights=low, minlength=len(uk))
    ok = np.isfinite(gz) & (n_low >= min_points)
    pure = np.zeros(len(uk), dtype=bool)
    for g in ground_labels:   # every low sample of the patch carries this one ground label
        pure |= np.bincount(inv, weights=low & (lab == g), minlength=len(uk)) == n_low
    ok &= pure
    height = np.bincount(inv, weights=np.where(low, p[:, 2], 0), minlength=len(uk)) / np.maximum(n_low, 1)
    return Patches(uk[ok].astype(np.float64) * size, height[ok], size)


def flat_patches_from_points(points: np.ndarray, size: float = PATCH, min_points: int = 200,
                             max_rms: float = 0.03, band: float = BAND, max_above: float = 0.02) -> Patches:
    """Without ground truth (real scans): patches where the lowest points (within `band` of the patch's 5th
    height percentile) hold at least `min_points` and fit one plane to `max_rms`, i.e. flat ground, and at most
    a `max_above` share of all the patch's points lie more than `band` above that ground: the counterpart of the
    labelled patches' "no object inside" (a parked car or a planter over flat ground is not a ground patch;
    what the mesh does under it is not the road's flatness). max_above = 1 keeps every flat-bottomed patch."""
    p = np.asarray(points, dtype=np.float64)
    key = np.floor(p[:, :2] / size).astype(np.int64)
    uk, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    order = np.lexsort((p[:, 2], inv))
    start = np.searchsorted(inv[order], np.arange(len(uk)))
    count = np.bincount(inv, minlength=len(uk))
    low = p[order[np.minimum(start + (0.05 * count).astype(np.int64), len(p) - 1)], 2]
    near = np.abs(p[:, 2] - low[inv]) < band
    rms, n = plane_rms(p[near], inv[near], len(uk))
    height = np.bincount(inv[near], weights=p[near, 2], minlength=len(uk)) / np.maximum(n, 1)
    above = np.bincount(inv, weights=p[:, 2] > height[inv] + band, minlength=len(uk)) / np.maximum(count, 1)
    ok = (n >= min_points) & (rms <= max_rms) & (above <= max_above)
    return Patches(uk[ok].astype(np.float64) * size, height[ok], size)


def plane_rms(points: np.ndarray, group: np.ndarray, n_groups: int) -> tuple[np.ndarray, np.ndarray]:
    """(RMS residual to the least-squares plane z = a x + b y + c of each group, points per group); NaN for
    groups with fewer than 3 points or collinear ones (`hgca_core.geometry.planes`)."""
    fit = fit_planes(points, group, n_groups)
    rms = np.sqrt(fit.rss / np.maximum(fit.weight, 1))
    return np.where(_defined(fit), rms, np.nan), np.round(fit.weight).astype(np.int64)


def _defined(fit: Planes) -> np.ndarray:
    """(G,) bool: the group's plane is defined (at least 3 points, not collinear)."""
    return (fit.weight >= 3) & (fit.det > 1e-12)


def ray_samples(mesh: trimesh.Trimesh, patches: Patches, spacing: float = 0.1, band: float = BAND
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertical rays on a `spacing` grid inside every patch (cell centres). Returns (patch index per ray (R,),
    number of mesh surfaces within `band` of the patch height (R,), first hit from above inside the band (R, 3),
    NaN where none)."""
    k = int(round(patches.size / spacing))
    o = (np.arange(k) + 0.5) * spacing
    offs = np.stack(np.meshgrid(o, o, indexing="ij"), -1).reshape(-1, 2)
    xy = (patches.corners[:, None, :] + offs[None]).reshape(-1, 2)
    pid = np.repeat(np.arange(len(patches.corners)), len(offs))
    top = patches.height[pid] + band
    origins = np.c_[xy, top + 1e-3]
    hits = np.zeros(len(xy), dtype=np.int64)
    first = np.full((len(xy), 3), np.nan)
    if len(mesh.faces) and len(xy):
        loc, ray, _ = mesh.ray.intersects_location(origins, np.tile([0.0, 0.0, -1.0], (len(xy), 1)),
                                                   multiple_hits=True)
        inside = loc[:, 2] >= patches.height[pid[ray]] - band
        loc, ray = loc[inside], ray[inside]
        # hits closer than 2 mm along one ray are one surface met at a shared edge or vertex
        order = np.lexsort((-loc[:, 2], ray))
        loc, ray = loc[order], ray[order]
        new = np.r_[True, (ray[1:] != ray[:-1]) | (loc[:-1, 2] - loc[1:, 2] > 2e-3)]
        hits = np.bincount(ray[new], minlength=len(xy))
        head = np.r_[True, ray[1:] != ray[:-1]]
        first[ray[head]] = loc[head]
    return pid, hits, first


def patch_planes(points: np.ndarray, patches: Patches, band: float = BAND) -> tuple[Planes, np.ndarray]:
    """(least-squares plane of each patch's points within `band` of its height, (P,) bool: the plane is defined,
    i.e. at least 3 such points, not collinear)."""
    p = np.asarray(points, dtype=np.float64)
    idx = patches.index(p)
    keep = idx >= 0
    keep[keep] &= np.abs(p[keep, 2] - patches.height[idx[keep]]) < band
    fit = fit_planes(p[keep], idx[keep], len(patches.corners))
    return fit, _defined(fit)


def ground_report(mesh: trimesh.Trimesh, patches: Patches, reference: dict[str, np.ndarray] | None = None,
                  spacing: float = 0.1, band: float = BAND, truth: np.ndarray | None = None) -> dict[str, float]:
    """Share of vertical rays meeting exactly one surface (and none, two or more), and the mean over patches of
    the plane-fit RMS residual of the mesh's first hits; for each named point set in `reference` (e.g. the
    input points, ground-truth samples) the same RMS on its points within `band` of each patch's height. With
    `truth` (ground-truth surface samples), also the RMS height error of the first hits against the plane of
    the truth's points in their patch (`rms_to_truth`): flat is not enough, it must also be where the road is."""
    pid, hits, first = ray_samples(mesh, patches, spacing, band)
    n_p = len(patches.corners)
    out = {"patches": float(n_p), "rays": float(len(pid)),
           "one_layer": float(np.mean(hits == 1)) if len(pid) else float("nan"),
           "no_layer": float(np.mean(hits == 0)) if len(pid) else float("nan"),
           "two_plus": float(np.mean(hits >= 2)) if len(pid) else float("nan")}
    ok = np.isfinite(first[:, 2])
    rms, n = plane_rms(first[ok], pid[ok], n_p)
    out["rms_mesh"] = float(np.nanmean(np.where(n >= 20, rms, np.nan))) if n_p else float("nan")
    for name, pts in (reference or {}).items():
        p = np.asarray(pts, dtype=np.float64)
        idx = patches.index(p)
        keep = idx >= 0
        keep[keep] &= np.abs(p[keep, 2] - patches.height[idx[keep]]) < band
        rms, n = plane_rms(p[keep], idx[keep], n_p)
        out[f"rms_{name}"] = float(np.nanmean(np.where(n >= 20, rms, np.nan))) if n_p else float("nan")
    if truth is not None:
        plane, defined = patch_planes(truth, patches, band)
        q, at = first[ok], pid[ok]
        err = np.where(defined[at], q[:, 2] - plane.height(at, q), np.nan)
        out["rms_to_truth"] = float(np.sqrt(np.nanmean(err ** 2))) if np.isfinite(err).any() else float("nan")
    return out

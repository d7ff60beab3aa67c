"""NumPy files: `.npy` holding an (N, >=3) table (or a structured array with x, y, z fields) and `.npz`
archives as written by `hgca read` (`points`, per-point attributes, optional `origins`, optional float64
`offset` added to `points`: see `hgca_core.io.georef`, optional `crs` and `unit` strings).

`hgca read` writes its .npz here (`write_accumulated`): float64 `points` relative to `offset`, `scan_index`,
`origin_index`, `origins` and the CRS, so that completing the .npz is completing what it was read from, bit for bit.
"""
from __future__ import annotations

import os
from typing import Mapping

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.atomic import atomic_write
from hgca_core.io.georef import local_offset, read_offset
from hgca_core.io.scan import Scan

READ_RESERVED = ("points", "origins", "offset", "crs", "unit", "unit_metres")  # `hgca read`'s non-attributes


def _numeric(a: np.ndarray, what: str, path: str) -> np.ndarray:
    if a.dtype.kind not in "biuf":
        raise InputError(f"{what} has non-numeric dtype {a.dtype}", path)
    return a


def _check_magic(path: str, magic: tuple[bytes, ...], what: str) -> None:
    with open(path, "rb") as f:
        head = f.read(8)
    if not head.startswith(magic):
        raise InputError(f"not a {what}: its first bytes lack the signature", path)


# A point table carries a few values per point (x, y, z, intensity, ring, time, colour: LAS's richest point
# format has 15 standard fields); more columns than this, and more than rows, look like points stored as columns.
MAX_COLUMNS = 16


def _refuse_wide(shape: tuple[int, ...], what: str, path: str) -> None:
    """An (R, C) table with 3 <= R < C and C > `MAX_COLUMNS` reads two ways: R points of C values, or C points
    stored as columns (x, y, z as rows, as MATLAB and some exporters save them). Neither is guessed."""
    rows, cols = shape
    if 3 <= rows < cols and cols > MAX_COLUMNS:
        raise InputError(f"{what} of shape {shape} has more columns than rows: it is either {rows} points with "
                         f"{cols} values each or {cols} points stored as columns; not read rather than guessed: "
                         f"save it as (N, {rows}) (the transpose, a.T) for {cols} points", path)


def read_npy(path: str) -> Scan:
    """Columns beyond x, y, z become attributes `column_3`, ...; structured arrays keep their field names."""
    _check_magic(path, (b"\x93NUMPY",), "NumPy .npy file")
    a = np.load(path, allow_pickle=False)
    if a.dtype.names:
        missing = [c for c in ("x", "y", "z") if c not in a.dtype.names]
        if missing or a.ndim != 1:
            raise InputError(f"structured array needs 1-D records with x, y, z fields (has {a.dtype.names})", path)
        points = np.column_stack([_numeric(a[c], c, path).astype(np.float64) for c in ("x", "y", "z")])
        attributes = {n: np.array(a[n]) for n in a.dtype.names
                      if n not in ("x", "y", "z") and a.dtype[n].shape == () and a.dtype[n].kind in "biuf"}
        return Scan(points, attributes, None, path)
    _numeric(a, "array", path)
    if a.ndim != 2 or a.shape[1] < 3:
        raise InputError(f"array must be (N, >=3), got shape {a.shape}", path)
    _refuse_wide(a.shape, "array", path)
    attributes = {f"column_{i}": a[:, i].copy() for i in range(3, a.shape[1])}
    return Scan(a[:, :3].astype(np.float64), attributes, None, path)


def read_npz(path: str) -> Scan:
    """Other (N,) arrays become attributes; arrays of any other shape are metadata and are ignored."""
    _check_magic(path, (b"PK\x03\x04", b"PK\x05\x06"), "NumPy .npz (zip) archive")
    with np.load(path, allow_pickle=False) as z:
        keys = list(z.keys())
        repeated = sorted({k for k in keys if keys.count(k) > 1})
        if repeated:
            raise InputError(f"npz holds array {repeated[0]!r} {keys.count(repeated[0])} times (a zip with repeated "
                             "member names): which one is meant is unknown", path)
        if "points" not in keys:
            raise InputError(f"npz has no 'points' array (keys: {keys})", path)
        points = _numeric(z["points"], "'points'", path)
        if points.ndim != 2 or points.shape[1] < 3:
            raise InputError(f"'points' must be (N, >=3), got shape {points.shape}", path)
        _refuse_wide(points.shape, "'points'", path)
        n = len(points)
        attributes = {}
        offset = read_offset(z["offset"], path) if "offset" in keys else np.zeros(3)
        for key in keys:
            if key in READ_RESERVED:
                continue
            value = z[key]
            if value.shape == (n,) and value.dtype.kind in "biuf":
                attributes[key] = value
        origins = None
        if "origins" in keys:
            origins = _numeric(z["origins"], "'origins'", path)
            if origins.ndim not in (1, 2) or origins.shape[-1] != 3:
                raise InputError(f"'origins' must be (S, 3), got shape {origins.shape}", path)
    return Scan(points[:, :3].astype(np.float64) + offset, attributes, origins, path)


def write_accumulated(path: str | os.PathLike, scan: Scan, attributes: Mapping[str, np.ndarray],
                      crs: str | None = None, unit: tuple[str, float | None] | None = None) -> str:
    """`hgca read`'s .npz: `points` (N,3) float64 relative to `offset` (3,) float64 (whole metres, as
    `georef.local_offset`; local numbers for the add-on, and `points + offset` gives the accumulated points back),
    the attributes (with `scan_index` and `origin_index`), `origins` (S,3) float64, and `crs` / `unit` (0-d
    strings) when the inputs declare them. Why float64: float32 moves points by up to a few micrometres, enough to
    put some in another cell, so completing the .npz gave another mesh than completing the scans themselves."""
    pts = np.asarray(scan.points, dtype=np.float64)
    offset = local_offset(pts)
    arrays: dict[str, np.ndarray] = {"points": pts - offset, "offset": offset}
    for name, values in attributes.items():
        if name in READ_RESERVED:
            raise ValueError(f"attribute name {name!r} is reserved")
        arrays[name] = np.asarray(values)
    if scan.origins is not None:
        arrays["origins"] = np.asarray(scan.origins, dtype=np.float64).reshape(-1, 3)
    if crs:
        arrays["crs"] = np.array(crs)
    if unit is not None:
        arrays["unit"] = np.array(unit[0])
        if unit[1] is not None:
            arrays["unit_metres"] = np.array(float(unit[1]))
    return atomic_write(os.fspath(path), lambda f: np.savez(f, **arrays))

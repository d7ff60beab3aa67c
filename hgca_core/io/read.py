"""`read_scan` / `read_scans`: the entry points every caller (CLI, pipeline, Blender via `hgca read`) uses.

Library exceptions from truncated or corrupt files are turned into `InputError` here, so callers only
ever see one error type whose message names the file.
"""
from __future__ import annotations

import os
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Callable, Iterator, Sequence

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.arrays import read_npy, read_npz
from hgca_core.io.av2 import read_av2_sweep
from hgca_core.io.formats import label, resolve_format
from hgca_core.io.georef import check_bound, check_coordinates
from hgca_core.io.las import read_las
from hgca_core.io.las_crs import check_inputs
from hgca_core.io.paths import check_readable
from hgca_core.io.pcd import read_pcd
from hgca_core.io.ply import read_ply
from hgca_core.io.poses import PoseEntry, load_poses, match_poses, validate_pose
from hgca_core.io.scan import Scan, finalize
from hgca_core.io.sensor_bin import read_kitti, read_nuscenes
from hgca_core.io.text import read_xyz

READERS: dict[str, Callable[[str], Scan]] = {
    "ply": read_ply, "las": read_las, "pcd": read_pcd, "xyz": read_xyz, "npy": read_npy, "npz": read_npz,
    "kitti": read_kitti, "nuscenes": read_nuscenes, "av2": read_av2_sweep,
}


def read_scan(path: str | os.PathLike, fmt: str | None = None) -> Scan:
    """Read one scan file; `fmt` overrides the extension (ply, las, pcd, xyz, npy, npz, kitti, nuscenes)."""
    path = os.fspath(path)
    check_readable(path)
    try:
        chosen = resolve_format(path, fmt)
    except OSError as exc:
        raise InputError(f"cannot open file ({exc.strerror})", path) from None
    try:
        scan = READERS[chosen](path)
    except InputError:
        raise
    except MemoryError:
        raise InputError("file is too large to read into memory", path) from None
    except Exception as exc:  # noqa: BLE001 - every parser failure is bad input, reported without a traceback
        raise InputError(f"corrupt or truncated {label(chosen)} file ({type(exc).__name__}: {exc})", path) from None
    return finalize(scan, path)


def _pose_list(poses: str | os.PathLike | Sequence, paths: list[str]) -> tuple[list[np.ndarray], list]:
    """Poses and JSON origins (or None) in `paths` order, from a JSON sidecar or a list of 4x4 arrays."""
    if isinstance(poses, (str, os.PathLike)):
        poses_path = os.fspath(poses)
        entries: list[PoseEntry] = match_poses(load_poses(poses_path), paths, poses_path)
        return [e.pose for e in entries], [e.origin for e in entries]
    mats = list(poses)
    if len(mats) != len(paths):
        names = ", ".join(os.path.basename(p) for p in paths[:5]) + (", ..." if len(paths) > 5 else "")
        raise InputError(f"{len(mats)} poses given for {len(paths)} scans ({names})")
    return [validate_pose(m, f"pose {i} (for {paths[i]})") for i, m in enumerate(mats)], [None] * len(mats)


def _own_rows(scan: Scan, origins: np.ndarray, own_labels: np.ndarray | None) -> np.ndarray | None:
    """Each point's row in this scan's own `origins`: its `origin_index`, else 0 for a single origin, else its
    own `scan_index` when there is one origin per scan (an accumulation `hgca read` wrote); None when unknown
    (`geometry.freespace.ray_origins` then takes the nearest origin, as before)."""
    index = scan.attributes.get("origin_index")
    if index is not None and len(index) and int(index.max()) < len(origins):
        return np.minimum(index.astype(np.int64), len(origins) - 1)
    if len(origins) == 1:
        return np.zeros(len(scan), dtype=np.int64)
    if own_labels is not None and int(own_labels.max()) + 1 == len(origins):
        return own_labels
    return None


def _origin_index(scans: list[Scan], origins: list[np.ndarray], labels: list[np.ndarray | None],
                  numbers: np.ndarray) -> np.ndarray | None:
    """Each point's row in the accumulated origins, where a scan gave its points' rows (`origin_index`) or they
    cannot be told from one origin per scan (`scan_index`) or a single origin, as `freespace.ray_origins` tells them."""
    rows = [_own_rows(s, o, own) for s, o, own in zip(scans, origins, labels)]
    if any(r is None for r in rows):
        return None
    start = np.cumsum([0] + [len(o) for o in origins[:-1]])
    index = np.concatenate([r + first for r, first in zip(rows, start)])
    total = int(start[-1]) + len(origins[-1])
    told = total == 1 or (total == int(numbers.max()) + 1 and np.array_equal(index, numbers))
    if told and not any("origin_index" in s.attributes for s in scans):
        return None
    return index.astype(np.uint16 if total <= 65536 else np.uint32)


def _own_labels(scan: Scan) -> np.ndarray | None:
    """A scan's own `scan_index` (non-negative integers), kept apart when it is itself an accumulation."""
    own = scan.attributes.get("scan_index")
    if own is None or not len(own) or own.dtype.kind not in "iu" or int(own.min()) < 0:
        return None
    return own.astype(np.int64)


def _scan_numbers(scans: list[Scan], labels: list[np.ndarray | None]) -> np.ndarray:
    """(N,) uint16 `scan_index`: scan i's points get the next number, and a scan that is an accumulation (its own
    `scan_index`) keeps its scans apart, numbered on in their order, so reading back what `hgca read` wrote
    gives the scans (and each scan's sensor) it was written from."""
    parts, base = [], 0
    for s, own in zip(scans, labels):
        if own is None:
            parts.append(np.full(len(s), base, dtype=np.int64))
            base += 1
            continue
        values, inverse = np.unique(own, return_inverse=True)
        parts.append(inverse.reshape(-1) + base)
        base += len(values)
    if base > np.iinfo(np.uint16).max + 1:
        raise InputError(f"too many scans ({base}, counting the scans within accumulated files); at most 65536 "
                         "can be accumulated")
    return np.concatenate(parts).astype(np.uint16)


def _refuse_mixed_origins(scans: list[Scan], names: list[str]) -> None:
    """Scans with and without sensor origins, read without poses, are refused.

    Why refuse rather than complete: the free-space rays need each point's sensor. An originless scan's points
    would be cast from another scan's sensor (the nearest origin), carving free space through walls that sensor
    never saw past; giving them no rays at all needs a "no sensor" mark the ray walk does not have. Refusing loses
    nothing: every file stays as it is, and the message says how to give the missing sensor position."""
    have = [s.origins is not None and len(s.origins) > 0 for s in scans]
    if any(have) and not all(have):
        without, with_ = names[have.index(False)], names[have.index(True)]
        raise InputError(f"this scan has no sensor origin but {with_} has one: its rays would be cast from "
                         f"another scan's sensor. Give every scan's sensor position (--poses, with an 'origin' "
                         f"where the sensor is not at the pose), or complete the scans without origins apart",
                         without)


def _refuse_repeats(paths: list[str]) -> None:
    """The same file twice (by name, through a symlink or a hard link) would count every point twice."""
    seen: dict[object, str] = {}
    for p in paths:
        try:
            st = os.stat(p)
            key: object = (st.st_dev, st.st_ino)
        except OSError:
            key = os.path.normcase(os.path.realpath(p))
        if key in seen:
            same = "" if seen[key] == p else f" (also given as {seen[key]})"
            raise InputError(f"scan file given twice{same}: its points would be counted twice", p)
        seen[key] = p


_KEEP_UNITS: ContextVar[bool] = ContextVar("hgca_keep_units", default=False)


@contextmanager
def keep_units() -> Iterator[None]:
    """Within it `read_scans` keeps files whose CRS is in feet or degrees as they are instead of refusing them:
    `hgca read` writes their own numbers with their CRS and unit, which completing the .npz then refuses."""
    token = _KEEP_UNITS.set(True)
    try:
        yield
    finally:
        _KEEP_UNITS.reset(token)


def read_scans(paths: Sequence[str | os.PathLike], poses: str | os.PathLike | Sequence | None = None,
               fmt: str | None = None, metric: bool | None = None) -> Scan:
    """Accumulate scan files in one world frame (`accumulate`), with poses from a JSON sidecar or 4x4 arrays.

    Files declaring different CRSs are refused, and with `metric` (what completing needs; the default outside
    `keep_units`) files whose CRS is not in metres (`las_crs.check_inputs`)."""
    if metric is None:
        metric = not _KEEP_UNITS.get()
    paths = [os.fspath(p) for p in paths]
    if not paths:
        raise InputError("no scan files given")
    if len(paths) > np.iinfo(np.uint16).max + 1:
        raise InputError(f"too many scans ({len(paths)}); at most 65536 can be accumulated")
    _refuse_repeats(paths)
    check_inputs(paths, metric)
    pose_mats, json_origins = _pose_list(poses, paths) if poses is not None else (None, None)
    scans = [read_scan(p, fmt) for p in paths]
    source = os.fspath(poses) if isinstance(poses, (str, os.PathLike)) else None
    return accumulate(scans, paths, pose_mats, json_origins, source)


def accumulate(scans: list[Scan], names: list[str], pose_mats: list[np.ndarray] | None = None,
               json_origins: list | None = None, source: str | None = None) -> Scan:
    """Scans (each in its sensor frame, or all in one frame without poses) in one world frame; adds
    `scan_index` (uint16; an accumulated file's own scans stay apart), `origin_index` (each point's row in the
    accumulated origins, wherever every scan tells it) and keeps the attributes all scans share.

    With poses, each scan's points go through its sensor->world pose and its origin is the JSON `origin`,
    else its own origins moved by the pose, else the pose translation. Without poses, points and origins
    are taken as already in one frame, and scans with and without origins are refused (`_refuse_mixed_origins`).
    `names` name the scans in messages (files, or a container's frames);
    `source` is the poses file, when there is one.
    """
    if not scans:
        raise InputError("no scans given")
    if len(scans) > np.iinfo(np.uint16).max + 1:
        raise InputError(f"too many scans ({len(scans)}); at most 65536 can be accumulated")
    if json_origins is None and pose_mats is not None:
        json_origins = [None] * len(pose_mats)
    if pose_mats is None:
        _refuse_mixed_origins(scans, names)
    common = set(scans[0].attributes)
    for s in scans[1:]:
        common &= set(s.attributes)
    common.discard("scan_index")
    points, origins = [], []
    any_origin = False
    for i, s in enumerate(scans):
        if pose_mats is None:
            points.append(s.points)
            if s.origins is not None:
                origins.append(s.origins)
                any_origin = True
            continue
        r, t = pose_mats[i][:3, :3], pose_mats[i][:3, 3]
        points.append(s.points @ r.T + t)
        if json_origins[i] is not None:
            origins.append(json_origins[i][None])
        elif s.origins is not None:
            origins.append(s.origins @ r.T + t)
        else:
            origins.append(t[None].copy())
        any_origin = True
    attributes = {name: np.concatenate([s.attributes[name] for s in scans]) for name in sorted(common)}
    labels = [_own_labels(s) for s in scans]
    attributes.pop("origin_index", None)
    attributes["scan_index"] = _scan_numbers(scans, labels)
    if len(origins) == len(scans):
        index = _origin_index(scans, origins, labels, attributes["scan_index"])
        if index is not None:
            attributes["origin_index"] = index
    accumulated = np.concatenate(points)
    if pose_mats is not None or len(scans) > 1:
        via = " moved by its pose" if pose_mats is not None else ""
        ends = np.cumsum([len(s) for s in scans])
        check_coordinates(accumulated, source, "accumulated point",
                          lambda row: f"scan {(i := int(np.searchsorted(ends, row, side='right')))}, {names[i]}{via}")
    if any_origin:
        check_bound(np.concatenate(origins), source, "sensor origin")
    return Scan(
        points=accumulated,
        attributes=attributes,
        origins=np.concatenate(origins) if any_origin else None,
        path=names[0] if len(names) == 1 else None,
        dropped={k: sum(s.dropped.get(k, 0) for s in scans) for k in sorted({k for s in scans for k in s.dropped})},
    )

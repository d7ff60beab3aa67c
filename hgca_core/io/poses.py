"""Per-scan sensor->world poses from the JSON sidecar in CONTRACTS.md, validated before any point moves.

A pose that is not a rigid transform (scaled, sheared, reflected, NaN) would silently distort the
accumulated scene, so it is rejected with the entry and the problem named. Scans find their entry by resolved
path (symlinks and `..` followed); only an entry that gives a bare file name may match a scan of that name in
another folder, with a warning, since sequences reuse names like `000003.bin` in every drive.
"""
from __future__ import annotations

import json
import os
import warnings
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from hgca_core.errors import HgcaWarning, InputError
from hgca_core.io.georef import COORD_LIMIT
from hgca_core.io.paths import check_readable

ORTHONORMAL_TOL = 1e-3  # max |R^T R - I| entry; loose enough for float32-rounded or SLAM-drifted rotations


@dataclass(frozen=True)
class PoseEntry:
    """One scan's pose: `file` as written in the JSON, `path` resolved against the JSON's folder."""

    file: str
    path: str
    pose: np.ndarray
    origin: np.ndarray | None


def validate_pose(matrix: Any, what: str, path: str | None = None) -> np.ndarray:
    """Return `matrix` as a float64 4x4 rigid transform, or raise InputError saying what is wrong."""
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{what}: pose is not a 4x4 array of numbers", path) from None
    if m.shape != (4, 4):
        raise InputError(f"{what}: pose must be 4x4, got shape {m.shape}", path)
    if not np.isfinite(m).all():
        raise InputError(f"{what}: pose has NaN or infinite values", path)
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise InputError(f"{what}: pose last row must be 0 0 0 1, got {m[3].tolist()}", path)
    r = m[:3, :3]
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > ORTHONORMAL_TOL:
        raise InputError(f"{what}: pose rotation is not orthonormal (max |R^T R - I| = {err:.3g})", path)
    if np.linalg.det(r) < 0:
        raise InputError(f"{what}: pose rotation is a reflection (determinant < 0)", path)
    if np.abs(m[:3, 3]).max() > COORD_LIMIT:
        raise InputError(f"{what}: pose translation {', '.join(f'{v:.6g}' for v in m[:3, 3])} lies beyond "
                         f"{COORD_LIMIT:.0e} m: no place on Earth in metres", path)
    return m


class _RepeatedKey(Exception):
    """A JSON object with one key twice."""


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _RepeatedKey(key)
        out[key] = value
    return out


def load_poses(path: str | os.PathLike) -> list[PoseEntry]:
    """Parse `{"scans": [{"file", "pose", "origin"?}, ...]}`; every entry is validated."""
    path = os.fspath(path)
    check_readable(path, "poses file")
    try:
        with open(path, "r", encoding="utf-8-sig") as f:
            doc = json.load(f, object_pairs_hook=_unique_keys)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"poses file is not valid JSON ({exc})", path) from None
    except _RepeatedKey as exc:
        raise InputError(f"poses file gives {exc.args[0]!r} twice in one object: JSON readers keep the later "
                         "one without a word, so which is meant is unknown", path) from None
    except RecursionError:
        raise InputError("poses file nests arrays or objects too deeply to be a poses file", path) from None
    scans = doc.get("scans") if isinstance(doc, dict) else None
    if not isinstance(scans, list) or not scans:
        raise InputError('poses JSON must be an object with a non-empty "scans" list', path)
    base = os.path.dirname(os.path.abspath(path))
    entries: list[PoseEntry] = []
    for i, item in enumerate(scans):
        what = f"scans[{i}]"
        if not isinstance(item, dict) or not isinstance(item.get("file"), str) or not item["file"].strip("\x00"):
            raise InputError(f'{what} must be an object with a "file" string', path)
        if "\x00" in item["file"]:
            raise InputError(f'{what}: "file" contains a NUL character', path)
        what = f"{what} ({item['file']})"
        if "pose" not in item:
            raise InputError(f'{what} has no "pose"', path)
        pose = validate_pose(item["pose"], what, path)
        origin = None
        if item.get("origin") is not None:
            try:
                origin = np.asarray(item["origin"], dtype=np.float64)
            except (TypeError, ValueError):
                origin = np.zeros(0)
            if origin.shape != (3,) or not np.isfinite(origin).all():
                raise InputError(f'{what}: "origin" must be 3 finite numbers', path)
        resolved = os.path.normpath(os.path.join(base, os.path.expanduser(item["file"])))
        entries.append(PoseEntry(item["file"], resolved, pose, origin))
    seen: dict[object, int] = {}
    for i, e in enumerate(entries):
        for key in _identities(e.path):
            if key in seen:
                j = seen[key]
                how = "" if entries[j].path == e.path else " (through a symlink or hard link)"
                differ = "" if np.array_equal(entries[j].pose, e.pose) else " with different poses"
                raise InputError(f"scans[{j}] ({entries[j].file}) and scans[{i}] ({e.file}) name the same file"
                                 f"{how}{differ}: give each scan one entry", path)
        for key in _identities(e.path):
            seen[key] = i
    return entries


def _identities(path: str) -> list[object]:
    """What makes two entries the same file: the resolved path, and the inode when the file exists."""
    keys: list[object] = [os.path.normpath(path), _key(path)]
    try:
        st = os.stat(path)
        keys.append((st.st_dev, st.st_ino))
    except OSError:
        pass
    return keys


def _key(path: str) -> str:
    return os.path.normcase(os.path.realpath(path))


def match_poses(entries: Sequence[PoseEntry], scan_paths: Sequence[str], poses_path: str) -> list[PoseEntry]:
    """The entry for each scan: the one whose `file` resolves to the same file (symlinks and `..` followed),
    else, with a warning, the one whose `file` is that bare file name (no folder part).

    Entries for scans not being read are allowed (importing a subset of a drive); a scan without an entry
    is an error, since guessing its pose would misplace it.
    """
    by_path = {_key(e.path): e for e in entries}
    result = []
    for scan in scan_paths:
        entry = by_path.get(_key(scan))
        if entry is None:
            name = os.path.basename(scan)
            bare = [e for e in entries if e.file == name]
            if len(bare) > 1:
                raise InputError(f"{len(bare)} entries have file name {name!r}; give the scan's path instead",
                                 poses_path)
            if not bare:
                elsewhere = [e.file for e in entries if os.path.basename(e.path) == name]
                hint = (f"; the entry {elsewhere[0]!r} names a file of that name in another folder"
                        if elsewhere else "")
                raise InputError(f"no pose for scan {scan!r} ({len(entries)} entries, {len(scan_paths)} scans{hint})",
                                 poses_path)
            entry = bare[0]
            warnings.warn(HgcaWarning(f"{poses_path}: no entry for the path of {scan}; using the entry {name!r} "
                                      f"by its file name alone (it resolves to {entry.path})"), stacklevel=2)
        if any(entry is r for r in result):
            raise InputError(f"two scans match the same entry {entry.file!r}", poses_path)
        result.append(entry)
    return result

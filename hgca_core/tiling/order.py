"""The order of a drive's scans, which is the path its tiles follow, whatever order the files were given in.

A shell glob lists `scan_10` before `scan_2`; taken as given, such an order makes the path zig-zag and lays
two tiles of opposite yaw over the same street (twice the work, and seams where none are needed). So the order
comes from what knows it:

1. a poses file: its entries' order (the sidecar lists the drive);
2. time stamps, when every scan has them (a per-point `gps_time`, `timestamp` or `time` attribute);
3. the file names in natural order (`scan_2` before `scan_10`), or the order given, whichever path is shorter;

and an order from 2 or 3 is kept only while its path is at most `CHAIN_SLACK` times as long as the chain of
nearest sensor positions (from one end of the drive, `chain`); otherwise that chain is the order. A sequence
folder (KITTI, Argoverse 2, nuScenes) is already in time order. A step between consecutive scans far longer than
the drive's usual one is reported (`warn_jumps`): tiles over a gap see none of it, and a wrong order shows so.
"""
from __future__ import annotations

import os
import re
import warnings
from typing import Sequence

import numpy as np

from hgca_core.errors import HgcaWarning

TIME_ATTRIBUTES = ("gps_time", "timestamp", "time")
CHAIN_SLACK = 1.5     # a drive that turns back on its own street is longer than its nearest-position chain
JUMP_FACTOR = 8.0     # a step this many times the median step between consecutive scans is a jump ...
JUMP_MIN = 20.0       # ... and at least this many metres (a drive scanned every 10 cm has no 80 cm jumps)
JUMPS_NAMED = 3       # jumps named in the warning; the rest are counted


def poses_order(paths: Sequence[str], poses: str | os.PathLike) -> list[int]:
    """Indices of `paths` in the order of their entries in the poses file (the entry each one reads with)."""
    from hgca_core.io.poses import load_poses, match_poses

    entries = load_poses(poses)
    with warnings.catch_warnings():            # reading the scans says it once, in the order chosen here
        warnings.simplefilter("ignore", HgcaWarning)
        matched = match_poses(entries, list(paths), os.fspath(poses))
    rank = {id(e): i for i, e in enumerate(entries)}
    return sorted(range(len(paths)), key=lambda i: rank[id(matched[i])])


def scan_time(attributes: dict[str, np.ndarray]) -> float | None:
    """When a scan was taken: the median of its first time attribute, or None without a finite one."""
    for name in TIME_ATTRIBUTES:
        values = attributes.get(name)
        if values is not None and len(values) and values.dtype.kind in "iuf":
            t = float(np.median(values))
            if np.isfinite(t):
                return t
    return None


def natural_key(name: str) -> list:
    """`scan_2` before `scan_10`: digit runs compare as numbers."""
    return [(0, int(part), "") if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", name) if part]


def path_length(positions: np.ndarray, order: Sequence[int]) -> float:
    """Metres (x/y) of the path through `positions` in `order`."""
    p = np.asarray(positions, dtype=np.float64)[list(order), :2]
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0


def chain(positions: np.ndarray, first: int = 0) -> list[int]:
    """Scans by the chain of nearest sensor positions: from each of the two far ends of the drive (the scan
    farthest from `first`, and the one farthest from that), always to the nearest scan not yet taken; the
    shorter chain, run from the end nearer to scan `first`."""
    xy = np.asarray(positions, dtype=np.float64).reshape(-1, 3)[:, :2]
    if len(xy) < 3:
        return list(range(len(xy)))
    a = int(np.argmax(np.linalg.norm(xy - xy[first], axis=1)))
    b = int(np.argmax(np.linalg.norm(xy - xy[a], axis=1)))
    best = min((_greedy(xy, a), _greedy(xy, b)), key=lambda o: path_length(positions, o))
    if np.linalg.norm(xy[best[-1]] - xy[first]) < np.linalg.norm(xy[best[0]] - xy[first]):
        best.reverse()
    return best


def _greedy(xy: np.ndarray, start: int) -> list[int]:
    free = np.ones(len(xy), dtype=bool)
    order = [start]
    free[start] = False
    for _ in range(len(xy) - 1):
        d = np.sum((xy - xy[order[-1]]) ** 2, axis=1)
        d[~free] = np.inf
        nxt = int(np.argmin(d))            # ties to the lower index: the same order on every machine
        order.append(nxt)
        free[nxt] = False
    return order


def order_scans(names: Sequence[str], positions: np.ndarray,
                times: Sequence[float | None]) -> tuple[list[int], str]:
    """The drive's order of scans given as `names` with sensor `positions` (S, 3) and `times` (None where a
    scan has none), and how it was found: "time", "names", "given" or "positions" (the module's rules 2-3)."""
    n = len(names)
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    given = list(range(n))
    if n < 3:
        return given, "given"
    candidates: list[tuple[list[int], str]] = []
    if all(t is not None for t in times) and len(set(times)) == n:
        candidates.append((sorted(given, key=lambda i: times[i]), "time"))
    else:
        by_name = sorted(given, key=lambda i: natural_key(names[i]))
        candidates += sorted([(given, "given"), (by_name, "names")], key=lambda c: path_length(pos, c[0]))
    linked = chain(pos, 0)
    limit = CHAIN_SLACK * path_length(pos, linked) + 1e-6
    for order, how in candidates:
        if path_length(pos, order) <= limit:
            return order, how
    return linked, "positions"


def jumps(positions: np.ndarray) -> tuple[list[tuple[int, float]], float]:
    """Steps (index of the scan before, metres) between consecutive positions longer than `JUMP_FACTOR` times
    the median step and `JUMP_MIN` metres; and the median step."""
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if len(p) < 2:
        return [], 0.0
    step = np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1)
    median = float(np.median(step))
    limit = max(JUMP_FACTOR * median, JUMP_MIN)
    return [(int(i), float(step[i])) for i in np.flatnonzero(step > limit)], median


def warn_jumps(names: Sequence[str], positions: np.ndarray) -> None:
    """One warning naming the scans between which the sensor jumps (the first few, and how many there are)."""
    found, median = jumps(positions)
    if not found:
        return
    short = [os.path.basename(n) for n in names]
    if len(set(short)) < len(short):                 # the same name in two folders: the paths tell them apart
        short = list(names)
    named = "; ".join(f"{short[i]} -> {short[i + 1]}: {d:.1f} m" for i, d in found[:JUMPS_NAMED])
    more = f" (and {len(found) - JUMPS_NAMED} more)" if len(found) > JUMPS_NAMED else ""
    warnings.warn(HgcaWarning(
        f"the sensor jumps between consecutive scans ({named}{more}; the median step is {median:.1f} m): tiles "
        "over a jump see none of it; check the scans' order (a poses file's order, else time stamps, else the "
        "chain of sensor positions) and their poses"), stacklevel=3)

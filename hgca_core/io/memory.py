"""Memory a read will need, known before reading: scans of 50 M points under a 3 GiB limit were read until the
allocator failed (a traceback, or the kernel's OOM killer without a word). The point count comes from what each
format states up front (fixed-size records, header counts); the limit is the tightest of the free memory, the
process's address-space limit and its cgroup's limit.
"""
from __future__ import annotations

import os
import re
import resource
from typing import Iterable

from hgca_core.errors import InputError

# Peak bytes per point of `hgca read` (float64 points, attributes, the local float32 copy and the writer's
# buffers): measured 66 B on a 4 M point KITTI .bin and 70 B on a 1 M point .xyz (37 MB interpreter baseline);
# with margin.
BYTES_PER_POINT = 80
BASE_BYTES = 64 * 2**20
RECORD_BYTES = {".bin": 16, ".pcd.bin": 20}   # KITTI x, y, z, intensity; nuScenes adds the ring, all float32


# The fewest bytes a point takes in each format (LAS records are at least 20 bytes, LAZ compresses them about
# tenfold, text needs "0 0 0\n"): a header claiming more points than its file can hold is the reader's to
# report as truncated, not a memory need.
MIN_POINT_BYTES = {".las": 20, ".laz": 2, ".ply": 6, ".pcd": 6, ".npy": 6}


def _header_count(path: str) -> int | None:
    """Points a PLY, PCD, LAS/LAZ or NPY file says it holds, from its first bytes, at most what its size can
    hold (compressed PCD excepted: it inflates); None when it does not say."""
    count = _claimed(path)
    if count is None:
        return None
    ext = os.path.splitext(path.lower())[1]
    try:
        with open(path, "rb") as f:
            compressed = ext == ".pcd" and b"DATA binary_compressed" in f.read(4096)
        size = os.path.getsize(path)
    except OSError:
        return None
    return count if compressed else min(count, size // MIN_POINT_BYTES[ext])


def _claimed(path: str) -> int | None:
    """The point count a header states."""
    name = path.lower()
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return None
    if name.endswith((".las", ".laz")) and head[:4] == b"LASF" and len(head) >= 255:
        legacy = int.from_bytes(head[107:111], "little")
        major, minor = head[24], head[25]
        modern = int.from_bytes(head[247:255], "little") if (major, minor) >= (1, 4) else 0
        return max(legacy, modern)
    if name.endswith(".ply"):
        m = re.search(rb"element\s+vertex\s+(\d+)", head)
        return int(m.group(1)) if m else None
    if name.endswith(".pcd"):
        m = re.search(rb"\nPOINTS\s+(\d+)", head)
        return int(m.group(1)) if m else None
    if name.endswith(".npy") and head[:6] == b"\x93NUMPY":
        m = re.search(rb"'shape':\s*\((\d+)", head)
        return int(m.group(1)) if m else None
    return None


def point_count_hint(paths: Iterable[str]) -> int:
    """Points the scan files hold, as far as their sizes and headers say (folders and other formats count 0)."""
    total = 0
    for p in paths:
        if not os.path.isfile(p):
            continue
        low = p.lower()
        record = RECORD_BYTES[".pcd.bin"] if low.endswith(".pcd.bin") else RECORD_BYTES.get(os.path.splitext(low)[1])
        if record is not None:
            total += os.path.getsize(p) // record
        else:
            total += _header_count(p) or 0
    return total


def memory_limit() -> tuple[int, str]:
    """(bytes this process can still allocate, what limits it): free memory, RLIMIT_AS, the cgroup's limit."""
    import psutil

    best, why = int(psutil.virtual_memory().available), "available"
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        room = soft - psutil.Process().memory_info().vms
        if room < best:
            best, why = max(room, 0), "left under the address-space limit (ulimit -v)"
    cgroup = _cgroup_room()
    if cgroup is not None and cgroup < best:
        best, why = cgroup, "left under the cgroup memory limit"
    return best, why


def _cgroup_room() -> int | None:
    try:
        with open("/proc/self/cgroup") as f:
            line = next((ln for ln in f if ln.startswith("0::")), None)
        if line is None:
            return None
        root = "/sys/fs/cgroup" + line.strip()[3:]
        with open(os.path.join(root, "memory.max")) as f:
            limit = f.read().strip()
        if limit == "max":
            return None
        with open(os.path.join(root, "memory.current")) as f:
            return int(limit) - int(f.read().strip())
    except (OSError, ValueError):
        return None


def check_read_memory(paths: Iterable[str]) -> None:
    """Refuse scans whose points cannot fit in memory, with the figures, before reading any of them."""
    points = point_count_hint(paths)
    need = BASE_BYTES + points * BYTES_PER_POINT
    room, why = memory_limit()
    if points and need > room:
        raise InputError(f"the scans hold about {points:,} points, which need about {need / 2**30:.1f} GiB to read; "
                         f"only {room / 2**30:.1f} GiB {why}: read fewer scans or frames, or crop them first")

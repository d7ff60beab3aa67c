"""LAS / LAZ / COPC via laspy (+ lazrs): scaled and offset coordinates, a few standard per-point fields.

Coordinates are `X * scale + offset` in float64 (laspy's scaled views), so UTM eastings and northings keep
the file's own precision. The header is checked before any point is read: a zero or non-finite scale makes
every point the same (corrupt), and a point count the file cannot hold (4.29 billion points in a few kB)
is a truncated or corrupt file, not a request to allocate 146 GB. Points are read in chunks, so memory only
grows with points that are really there.
"""
from __future__ import annotations

import io
import os
from typing import Any

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.scan import Scan

# Per-point fields worth carrying (intensity and RGB for display, returns and class for filtering, time for ordering).
LAS_ATTRIBUTES = ("intensity", "return_number", "classification", "gps_time", "red", "green", "blue")


CHUNK = 1 << 20


def check_header(header: Any, path: str) -> None:
    """Scale, offset and point count against what a sane file of this size can hold."""
    for axis, scale, offset in zip("xyz", header.scales, header.offsets):
        if not np.isfinite(scale) or scale == 0:
            raise InputError(f"corrupt LAS header: {axis} scale is {scale} (every point would get the same {axis})",
                             path)
        if not np.isfinite(offset):
            raise InputError(f"corrupt LAS header: {axis} offset is {offset}", path)
    count = int(header.point_count)
    if not header.are_points_compressed:
        record = int(header.point_format.size)
        need = int(header.offset_to_point_data) + count * record
        size = os.path.getsize(path)
        if need > size:
            raise InputError(f"truncated or corrupt LAS file: header says {count} points ({need} bytes with the "
                             f"header), the file has {size} bytes", path)
        after = [int(getattr(header, name, 0) or 0) for name in ("start_of_first_evlr",
                                                                   "start_of_waveform_data_packet_record")]
        end = min([a for a in after if a >= need] + [size])
        if end - need >= record:
            raise InputError(f"LAS header says {count} points but the file holds {count + (end - need) // record} "
                             f"point records ({end - need} bytes after the first {count}): the header's point count "
                             "is wrong, reading it would drop points", path)


def read_las(path: str) -> Scan:
    """Read every point; a file holding fewer points than its header promises is truncated or corrupt, one
    holding more (a header count that lies low) is refused too."""
    import laspy

    with laspy.open(path) as reader:
        header = reader.header
        check_header(header, path)
        count = int(header.point_count)
        stored = laz_stored_points(path, header) if header.are_points_compressed else None
        if stored is not None:
            raise InputError(f"LAZ header says {count} points but its compressed data holds {stored}: the header's "
                             "point count is wrong, reading it would drop points", path)
        present = set(header.point_format.dimension_names)
        names = [name for name in LAS_ATTRIBUTES if name in present]
        xyz: list[np.ndarray] = []
        columns: dict[str, list[np.ndarray]] = {name: [] for name in names}
        read = 0
        try:
            for chunk in reader.chunk_iterator(CHUNK):
                xyz.append(np.column_stack([np.asarray(chunk.x, dtype=np.float64), np.asarray(chunk.y, dtype=np.float64),
                                            np.asarray(chunk.z, dtype=np.float64)]))
                for name in names:
                    columns[name].append(np.array(chunk[name]))
                read += len(chunk)
        except MemoryError:
            raise
        except Exception as exc:  # noqa: BLE001 - lazrs/laspy raise many types for a file that ends early
            raise InputError(f"truncated or corrupt LAS/LAZ file: header says {count} points, reading stopped "
                             f"after {read} ({type(exc).__name__}: {exc})", path) from None
    if read != count:
        raise InputError(f"truncated LAS/LAZ file: header says {count} points, file holds {read}", path)
    points = np.concatenate(xyz) if xyz else np.zeros((0, 3))
    attributes = {name: np.concatenate(parts) for name, parts in columns.items() if parts}
    return Scan(points, attributes, None, path)


def laz_stored_points(path: str, header: Any) -> str | None:
    """None when the LAZ chunks hold exactly the header's point count (or cannot be checked), else how many
    they hold, in words. Needs the header before any point is read (laspy drops the LASzip VLR then).

    The chunk table gives each chunk's byte size (and, for variable-size chunks as in COPC, its point count).
    LAZ coding is deterministic, so the header's share of points in the last fixed-size chunk, compressed again,
    takes exactly that chunk's bytes when the count is right (so it does for every real LAZ here, LASzip's and
    lazrs'); fewer bytes mean the chunk holds more points than the header counts. A file without a readable
    chunk table is taken as it is."""
    import lazrs

    count = int(header.point_count)
    vlr = next((v for v in header.vlrs if getattr(v, "user_id", "") == "laszip encoded"), None)
    if vlr is None or count == 0:
        return None
    try:
        data = vlr.record_data_bytes()
        laz = lazrs.LazVlr(data)
        with open(path, "rb") as f:
            f.seek(int(header.offset_to_point_data))
            table = lazrs.read_chunk_table(f, laz)
    except Exception:  # noqa: BLE001 - no chunk table (old writers, streamed files): nothing to compare
        return None
    if not table:
        return None
    if laz.uses_variable_size_chunks():
        total = sum(int(n) for n, _ in table)
        return None if total == count else str(total)
    size, chunks = int(laz.chunk_size()), len(table)
    first = (chunks - 1) * size
    if count <= first:
        return f"{chunks} chunks ({first} points in the first {chunks - 1} alone)"

    def packed_bytes(n: int) -> int:
        """Bytes of the last chunk's first n points compressed again (raises when n is past its data)."""
        with open(path, "rb") as f:
            f.seek(int(header.offset_to_point_data))
            reader = lazrs.LasZipDecompressor(f, data)
            reader.seek(first)
            out = bytearray(n * laz.item_size())
            reader.decompress_many(out)
        packed = bytes(lazrs.compress_points(laz, bytes(out), False))
        return int(lazrs.read_chunk_table(io.BytesIO(packed), laz)[0][1])

    want = int(table[-1][1])
    try:
        if packed_bytes(count - first) >= want:
            return None
    except Exception:  # noqa: BLE001 - a chunk lazrs cannot code again: leave the check out
        return None
    lo, hi = count - first + 1, size     # the smallest share of the chunk that fills its bytes
    while lo < hi:
        mid = (lo + hi) // 2
        try:
            full = packed_bytes(mid) >= want
        except Exception:  # noqa: BLE001 - decoding past the chunk's data
            full = True
        lo, hi = (lo, mid) if full else (mid + 1, hi)
    try:
        exact = packed_bytes(lo) == want
    except Exception:  # noqa: BLE001
        exact = False
    return str(first + lo) if exact else f"more than {count}"


def las_header_info(path: str) -> dict[str, Any]:
    """Header facts `hgca info` shows (version, point format, counts, scale, offset) without reading points."""
    import laspy

    from hgca_core.io.las_crs import header_crs

    with laspy.open(path) as reader:
        h = reader.header
        vlr_ids = {(v.user_id, v.record_id) for v in h.vlrs}
        return {
            "version": f"{h.version.major}.{h.version.minor}",
            "point_format": int(h.point_format.id),
            "header_point_count": int(h.point_count),
            "scale": [float(v) for v in h.scales],
            "offset": [float(v) for v in h.offsets],
            "compressed": bool(h.are_points_compressed),
            "copc": ("copc", 1) in vlr_ids,
            "header_min": [float(v) for v in h.mins],
            "header_max": [float(v) for v in h.maxs],
            "crs": header_crs(h),
        }

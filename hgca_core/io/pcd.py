"""PCL's PCD format (ascii, binary, binary_compressed), parsed here so no PCL/Open3D is needed to read it.

Fields x, y, z become the points; every other field becomes an attribute (fields with COUNT > 1 are split
into `name_0 ... name_k`, packed `rgb`/`rgba` floats into uint8 channels, `_` padding fields are skipped).
A non-default VIEWPOINT gives the sensor origin.

The header must agree with the data: POINTS with WIDTH x HEIGHT, and the data with POINTS (no rows or bytes
beyond them, none missing). A disagreement means the file was cut, padded or written wrongly, and reading
"what fits" would silently drop or invent points, so it is refused with the header field named.
"""
from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.lzf import LZFError, lzf_decompress
from hgca_core.io.scan import Scan

_TYPES = {("F", 4): "<f4", ("F", 8): "<f8", ("I", 1): "i1", ("I", 2): "<i2", ("I", 4): "<i4", ("I", 8): "<i8",
          ("U", 1): "u1", ("U", 2): "<u2", ("U", 4): "<u4", ("U", 8): "<u8"}
_MAX_HEADER = 1 << 16
_DEFAULT_VIEWPOINT = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


@dataclass
class PCDHeader:
    fields: list[str]
    dtypes: list[np.dtype]
    counts: list[int]
    width: int
    height: int
    points: int
    viewpoint: tuple[float, ...]
    data: str
    data_offset: int


def parse_header(raw: bytes, path: str) -> PCDHeader:
    """Parse header lines up to and including DATA; checks that FIELDS/SIZE/TYPE/COUNT agree."""
    entries: dict[str, list[str]] = {}
    pos = 3 if raw.startswith(b"\xef\xbb\xbf") else 0      # a UTF-8 byte-order mark before the header
    while True:
        end = raw.find(b"\n", pos)
        if end < 0 or pos > _MAX_HEADER:
            raise InputError("PCD header has no DATA line (truncated or not a PCD file)", path)
        line = raw[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        if key.upper() in entries:
            raise InputError(f"PCD header has two {key.upper()} lines (which one is meant is unknown)", path)
        entries[key.upper()] = values
        if key.upper() == "DATA":
            break
    for key in ("FIELDS", "SIZE", "TYPE", "WIDTH", "HEIGHT"):
        if key not in entries:
            raise InputError(f"PCD header lacks {key}", path)
    fields = entries["FIELDS"]
    n = len(fields)
    repeated = sorted({f for f in fields if fields.count(f) > 1 and f != "_"})
    if repeated:
        raise InputError(f"PCD FIELDS lists {repeated[0]!r} {fields.count(repeated[0])} times (fields: "
                         f"{' '.join(fields)}): which column is {repeated[0]} is unknown", path)
    counts_raw = entries.get("COUNT", ["1"] * n)
    if not (len(entries["SIZE"]) == len(entries["TYPE"]) == len(counts_raw) == n):
        raise InputError("PCD header FIELDS, SIZE, TYPE and COUNT have different lengths", path)
    try:
        sizes = [int(s) for s in entries["SIZE"]]
        counts = [int(c) for c in counts_raw]
        width, height = int(entries["WIDTH"][0]), int(entries["HEIGHT"][0])
        points = int(entries["POINTS"][0]) if "POINTS" in entries else width * height
        viewpoint = tuple(float(v) for v in entries.get("VIEWPOINT", _DEFAULT_VIEWPOINT))
    except (ValueError, IndexError) as exc:
        raise InputError(f"PCD header has a malformed number ({exc})", path) from None
    dtypes = []
    for name, t, s in zip(fields, entries["TYPE"], sizes):
        code = _TYPES.get((t.upper(), s))
        if code is None:
            raise InputError(f"PCD field {name!r} has unsupported TYPE {t} with SIZE {s}", path)
        dtypes.append(np.dtype(code))
    if min(counts) < 1 or points < 0 or len(viewpoint) != 7:
        raise InputError("PCD header has invalid COUNT, POINTS or VIEWPOINT", path)
    if not np.isfinite(viewpoint).all():
        raise InputError(f"PCD VIEWPOINT has NaN or infinite values ({' '.join(entries['VIEWPOINT'])}): the "
                         "sensor position is unknown", path)
    if width < 0 or height < 0:
        raise InputError(f"PCD header WIDTH {width} / HEIGHT {height} must not be negative", path)
    if width * height != points:
        raise InputError(f"PCD header POINTS {points} disagrees with WIDTH x HEIGHT = {width} x {height} "
                         f"= {width * height}", path)
    mode = entries["DATA"][0].lower() if entries["DATA"] else ""
    if mode not in ("ascii", "binary", "binary_compressed"):
        raise InputError(f"PCD DATA {mode!r} is not ascii, binary or binary_compressed", path)
    for c in ("x", "y", "z"):
        if c not in fields:
            raise InputError(f"PCD has no field {c!r} (fields: {fields})", path)
        if counts[fields.index(c)] != 1:
            raise InputError(f"PCD field {c!r} has COUNT != 1", path)
    return PCDHeader(fields, dtypes, counts, width, height, points, viewpoint, mode, pos)


def _columns_ascii(body: bytes, h: PCDHeader, path: str) -> list[np.ndarray]:
    width = sum(h.counts)
    text = body.decode("ascii", errors="replace")
    table = np.zeros((0, width))
    if text.strip():
        try:
            table = np.loadtxt(io.StringIO(text), dtype=np.float64, ndmin=2, comments="#")
        except ValueError as exc:
            raise InputError(f"PCD ascii data is malformed ({exc})", path) from None
        if table.shape[1] != width:
            raise InputError(f"PCD ascii rows have {table.shape[1]} values, header says {width}", path)
    if len(table) < h.points:
        raise InputError(f"truncated: header POINTS says {h.points} points, ascii data holds {len(table)}", path)
    if len(table) > h.points:
        raise InputError(f"PCD header POINTS says {h.points} points, the ascii data has {len(table)} rows", path)
    cols, start = [], 0
    for dt, count in zip(h.dtypes, h.counts):
        block = table[:, start : start + count]
        cols.append(block[:, 0].astype(dt) if count == 1 else block.astype(dt))
        start += count
    return cols


def _check_tail(tail: bytes, record: int, points: int, path: str) -> None:
    """Bytes after the data POINTS announces: a final newline is harmless, anything else is refused."""
    if tail and not (len(tail) < record and not tail.strip(b" \t\r\n")):
        raise InputError(f"PCD data has {len(tail)} bytes after the {points} points of the header's POINTS "
                         "(trailing garbage, or POINTS is wrong)", path)


def _columns_binary(body: bytes, h: PCDHeader, path: str) -> list[np.ndarray]:
    record = np.dtype([(f"f{i}", dt, (c,)) if c > 1 else (f"f{i}", dt)
                       for i, (dt, c) in enumerate(zip(h.dtypes, h.counts))])
    need = record.itemsize * h.points
    if len(body) < need:
        raise InputError(f"truncated: binary data holds {len(body)} bytes, {h.points} points need {need}", path)
    _check_tail(body[need:], record.itemsize, h.points, path)
    table = np.frombuffer(body, dtype=record, count=h.points)
    return [np.array(table[f"f{i}"]) for i in range(len(h.fields))]


def _columns_compressed(body: bytes, h: PCDHeader, path: str) -> list[np.ndarray]:
    if len(body) < 8:
        raise InputError("truncated: binary_compressed data lacks its size words", path)
    compressed, uncompressed = (int(v) for v in np.frombuffer(body[:8], dtype="<u4"))
    sizes = [dt.itemsize * c for dt, c in zip(h.dtypes, h.counts)]
    need = sum(sizes) * h.points
    if uncompressed != need:
        raise InputError(f"binary_compressed says {uncompressed} bytes uncompressed, {h.points} points need {need}",
                         path)
    if len(body) - 8 < compressed:
        raise InputError(f"truncated: binary_compressed holds {len(body) - 8} of {compressed} compressed bytes", path)
    _check_tail(body[8 + compressed:], sum(sizes), h.points, path)
    if need == 0:
        return [np.zeros((0, c) if c > 1 else 0, dtype=dt) for dt, c in zip(h.dtypes, h.counts)]
    try:
        raw = lzf_decompress(body[8 : 8 + compressed], need)
    except LZFError as exc:
        raise InputError(f"corrupt binary_compressed data: {exc}", path) from None
    cols, start = [], 0
    for dt, c, size in zip(h.dtypes, h.counts, sizes):  # column-major: all values of one field, then the next
        chunk = np.frombuffer(raw, dtype=dt, count=h.points * c, offset=start)
        cols.append(chunk.reshape(h.points, c).copy() if c > 1 else chunk.copy())
        start += size * h.points
    return cols


def read_pcd(path: str) -> Scan:
    """Read a PCD file of any DATA mode into a Scan (NaN placeholder rows are handled by `finalize`)."""
    with open(path, "rb") as f:
        raw = f.read()
    h = parse_header(raw, path)
    body = raw[h.data_offset :]
    reader = {"ascii": _columns_ascii, "binary": _columns_binary, "binary_compressed": _columns_compressed}[h.data]
    cols = reader(body, h, path)
    index = {name: i for i, name in enumerate(h.fields)}
    points = np.column_stack([cols[index[c]].astype(np.float64) for c in ("x", "y", "z")])
    attributes: dict[str, np.ndarray] = {}
    for i, name in enumerate(h.fields):
        if name in ("x", "y", "z") or name == "_":
            continue
        values = cols[i]
        if name in ("rgb", "rgba") and h.counts[i] == 1 and h.dtypes[i].itemsize == 4:
            packed = values.view(np.uint32) if values.dtype.kind == "f" else values.astype(np.uint32)
            attributes["red"] = ((packed >> 16) & 0xFF).astype(np.uint8)
            attributes["green"] = ((packed >> 8) & 0xFF).astype(np.uint8)
            attributes["blue"] = (packed & 0xFF).astype(np.uint8)
            if name == "rgba":
                attributes["alpha"] = ((packed >> 24) & 0xFF).astype(np.uint8)
        elif values.ndim == 2:
            for k in range(values.shape[1]):
                attributes[f"{name}_{k}"] = values[:, k].copy()
        else:
            attributes[name] = values
    origins = None
    if any(abs(a - b) > 0 for a, b in zip(h.viewpoint, _DEFAULT_VIEWPOINT)):
        origins = np.array([h.viewpoint[:3]], dtype=np.float64)
    return Scan(points, attributes, origins, path)

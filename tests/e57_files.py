"""Writing E57 files for tests through libE57Format directly, for what pye57's `write_scan_raw` cannot write:
double-precision (georeferenced) coordinates, spherical-only scans, scans without coordinates, 16-bit colour,
any pose quaternion (zero, NaN) and scans whose every point is invalid."""
from __future__ import annotations

import uuid
from pathlib import Path

import numpy as np

SCAN_KEYS = ("rotation", "translation", "intensity_limits", "colour_max")  # the rest are point fields

def write_e57(path: Path, scans: list[dict]) -> Path:
    """Each scan a dict of point fields (E57 names -> (N,) arrays: cartesianX.., sphericalRange.., intensity,
    colorRed.., cartesianInvalidState), with optional "rotation" (w, x, y, z), "translation", "intensity_limits"
    (min, max) and "colour_max" (255 or 65535). No "rotation" and no "translation": the scan has no pose."""
    import pye57
    from pye57 import libe57 as lib

    e57 = pye57.E57(str(path), mode="w")  # writes the standard file header
    imf = e57.image_file
    try:
        for i, spec in enumerate(scans):
            fields = {k: np.asarray(v) for k, v in spec.items() if k not in SCAN_KEYS}
            node = lib.StructureNode(imf)
            node.set("guid", lib.StringNode(imf, "{%s}" % uuid.uuid4()))
            node.set("name", lib.StringNode(imf, f"scan {i}"))
            if "rotation" in spec or "translation" in spec:
                pose = lib.StructureNode(imf)
                rot, tr = lib.StructureNode(imf), lib.StructureNode(imf)
                for k, v in zip("wxyz", spec.get("rotation", (1.0, 0.0, 0.0, 0.0))):
                    rot.set(k, lib.FloatNode(imf, float(v)))
                for k, v in zip("xyz", spec.get("translation", (0.0, 0.0, 0.0))):
                    tr.set(k, lib.FloatNode(imf, float(v)))
                pose.set("rotation", rot)
                pose.set("translation", tr)
                node.set("pose", pose)
            if "intensity_limits" in spec:
                limits = lib.StructureNode(imf)
                limits.set("intensityMinimum", lib.FloatNode(imf, float(spec["intensity_limits"][0])))
                limits.set("intensityMaximum", lib.FloatNode(imf, float(spec["intensity_limits"][1])))
                node.set("intensityLimits", limits)
            proto = lib.StructureNode(imf)
            for name, values in fields.items():
                if name.startswith("color"):
                    proto.set(name, lib.IntegerNode(imf, 0, 0, int(spec.get("colour_max", 255))))
                elif name.endswith("InvalidState"):
                    proto.set(name, lib.IntegerNode(imf, 0, 0, 2))
                else:
                    proto.set(name, lib.FloatNode(imf, 0.0, lib.E57_DOUBLE))
            points = lib.CompressedVectorNode(imf, proto, lib.VectorNode(imf, True))
            node.set("points", points)
            e57.data3d.append(node)
            n = len(next(iter(fields.values())))
            arrays = {name: np.ascontiguousarray(values, dtype=_dtype(name, spec)) for name, values in fields.items()}
            buffers = lib.VectorSourceDestBuffer()
            for name, array in arrays.items():
                buffers.append(lib.SourceDestBuffer(imf, name, array, n, True, True))
            writer = points.writer(buffers)
            writer.write(n)
            writer.close()
    finally:
        e57.close()
    return path


def _dtype(name: str, spec: dict) -> type:
    if name.startswith("color"):
        return np.uint16 if spec.get("colour_max", 255) > 255 else np.uint8
    return np.int8 if name.endswith("InvalidState") else np.float64


def cartesian(points: np.ndarray, **extra) -> dict:
    """A scan dict of (N, 3) points plus `extra` fields / pose keys."""
    pts = np.asarray(points, dtype=np.float64)
    return {"cartesianX": pts[:, 0], "cartesianY": pts[:, 1], "cartesianZ": pts[:, 2], **extra}


def _crc32c(data: bytes) -> int:
    """CRC-32C (Castagnoli), the checksum E57 keeps in the last 4 bytes of every 1024-byte page."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def float_text(value: float) -> bytes:
    """How libE57 writes a float element's value in the file's XML."""
    return f"{value:.17e}".encode()


def patch_xml(path: Path, old: bytes, new: bytes) -> None:
    """Replace `old` (within one page of the XML section) by `new` padded with spaces, and fix the page's
    checksum: a file as an exporter that writes such a value would make it (libE57 cannot write NaN)."""
    data = bytearray(Path(path).read_bytes())
    at = data.find(old)
    assert at >= 0 and data.find(old, at + 1) < 0 and len(new) <= len(old), (old, new)
    data[at:at + len(old)] = new.ljust(len(old))
    page = at // 1024 * 1024
    assert (at + len(old) - 1) // 1024 * 1024 == page and at + len(old) <= page + 1020, "value crosses a page"
    data[page + 1020:page + 1024] = _crc32c(bytes(data[page:page + 1020])).to_bytes(4, "big")
    Path(path).write_bytes(bytes(data))

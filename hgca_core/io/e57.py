"""E57 files (ASTM E2807) as a sequence: one frame per scan, each in its own frame with the pose the file gives it.

Terrestrial and mobile-mapping scanners export E57: several scans in one file, each with a rigid pose (a unit
quaternion w, x, y, z and a translation, scan -> file frame), points as cartesian or spherical coordinates, and
often intensity and colour. A scan's points are read in its own frame, its pose goes with the frame, and
`accumulate` moves them to the file frame in float64, so projected (UTM) coordinates stay exact whether the file
puts them in the points or in the poses. The scanner sits at each scan's origin, which is what free space needs.

The file is read through libE57Format (pye57's `libe57`, the `recordings` extra); its page checksums catch
truncated and corrupt files, and every library error becomes one InputError naming the file and the scan.
"""
from __future__ import annotations

from contextlib import contextmanager
from typing import Any, Iterator

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.av2 import quat_pose
from hgca_core.io.paths import check_readable
from hgca_core.io.poses import validate_pose
from hgca_core.io.scan import Scan, finalize
from hgca_core.io.sequence import Sequence

SIGNATURE = b"ASTM-E57"
CARTESIAN = ("cartesianX", "cartesianY", "cartesianZ")
SPHERICAL = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
COLOURS = {"colorRed": "red", "colorGreen": "green", "colorBlue": "blue"}
INVALID = "invalid points (E57 invalid state)"  # the key of Scan.dropped
CHUNK = 1 << 20  # points per read: buffers of ~30 MB whatever the scan's size
# Other formats whose files get renamed to .e57 by mistake, by their first bytes.
OTHER_SIGNATURES = ((b"LASF", "LAS/LAZ"), (b"ply", "PLY"), (b"# .PCD", "PCD"), (b"PK", "ZIP"))


def _libe57(path: str) -> Any:
    try:
        from pye57 import libe57
    except ImportError:
        raise InputError("reading E57 files needs the recordings extra (pip install 'hgca[recordings]')",
                         path) from None
    return libe57


def _first_line(exc: BaseException) -> str:
    """libE57's messages carry a multi-line debug dump after the first line; the first line says what is wrong."""
    text = str(exc).strip()
    return text.splitlines()[0].strip() if text else type(exc).__name__


def check_signature(path: str) -> None:
    """An E57 file starts with 'ASTM-E57'; anything else (a renamed LAS, a text file) is named as such."""
    check_readable(path)
    with open(path, "rb") as f:
        head = f.read(len(SIGNATURE))
    if head != SIGNATURE:
        other = next((name for magic, name in OTHER_SIGNATURES if head.startswith(magic)), None)
        raise InputError("not an E57 file: it does not start with the ASTM-E57 signature"
                         + (f" (its content is {other})" if other else ""), path)


@contextmanager
def _image(path: str) -> Iterator[tuple[Any, Any]]:
    """(libe57, an open ImageFile): closed on the way out, a library failure is an InputError."""
    check_signature(path)
    lib = _libe57(path)
    try:
        imf = lib.ImageFile(path, "r")
    except lib.E57Exception as exc:
        raise InputError(f"corrupt or truncated E57 file ({_first_line(exc)})", path) from None
    try:
        yield lib, imf
    finally:
        imf.close()


def _scan_nodes(imf: Any, path: str) -> list[Any]:
    root = imf.root()
    if not root.isDefined("data3D") or root["data3D"].childCount() == 0:
        raise InputError("E57 file holds no scans (its data3D list is empty)", path)
    data3d = root["data3D"]
    return [data3d[i] for i in range(data3d.childCount())]


def _number(lib: Any, node: Any) -> float:
    return float(node.scaledValue() if isinstance(node, lib.ScaledIntegerNode) else node.value())


def scan_pose(lib: Any, scan: Any, i: int, path: str) -> np.ndarray:
    """Scan -> file frame 4x4 (float64); identity without a pose. A zero or non-finite quaternion is refused:
    there is no rotation to take from it, and a guess would place the scan anywhere."""
    if not scan.isDefined("pose"):
        return np.eye(4)
    pose = scan["pose"]
    q, t = np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3)
    try:
        if pose.isDefined("rotation"):
            q = np.array([_number(lib, pose["rotation"][k]) for k in "wxyz"])
        if pose.isDefined("translation"):
            t = np.array([_number(lib, pose["translation"][k]) for k in "xyz"])
    except lib.E57Exception as exc:
        raise InputError(f"scan {i}: pose is incomplete ({_first_line(exc)})", path) from None
    shown = ", ".join(f"{v:.6g}" for v in q)
    norm = float(np.linalg.norm(q)) if np.isfinite(q).all() else np.inf
    if not np.isfinite(norm):  # libE57 reads 'nan' as 0 and an overflow (1e999) as the largest double
        raise InputError(f"scan {i}: pose rotation quaternion (w, x, y, z) = ({shown}) is not finite", path)
    if norm < 1e-6:  # also an all-'nan' quaternion, as libE57 reads it
        raise InputError(f"scan {i}: pose rotation quaternion (w, x, y, z) = ({shown}) is zero: it is no rotation",
                         path)
    if not np.isfinite(t).all():
        raise InputError(f"scan {i}: pose translation ({', '.join(f'{v:.6g}' for v in t)}) is not finite", path)
    return validate_pose(quat_pose(q, t), f"scan {i}", path)


def _prototype(lib: Any, scan: Any, i: int, path: str) -> tuple[Any, dict[str, Any]]:
    """(the scan's points node, its fields by name); a scan without coordinates is refused."""
    if not scan.isDefined("points") or not isinstance(scan["points"], lib.CompressedVectorNode):
        raise InputError(f"scan {i} has no points", path)
    points = scan["points"]
    proto = lib.StructureNode(points.prototype())
    names = [proto.get(k).elementName() for k in range(proto.childCount())]
    fields = {name: proto[name] for name in names}  # indexing by name gives the typed node
    if not (set(CARTESIAN) <= fields.keys() or set(SPHERICAL) <= fields.keys()):
        raise InputError(f"scan {i} has neither cartesian (cartesianX/Y/Z) nor spherical (sphericalRange/Azimuth/"
                         f"Elevation) coordinates; its fields: {', '.join(fields) or 'none'}", path)
    return points, fields


def _colour_dtype(lib: Any, node: Any) -> np.dtype:
    """uint8 or uint16 as the file stores colour (its declared maximum), float32 for float colour."""
    if isinstance(node, lib.FloatNode):
        return np.dtype(np.float32)
    top = node.maximum()
    if isinstance(node, lib.ScaledIntegerNode):
        top = node.scale() * top + node.offset()
    return np.dtype(np.uint8 if top <= 255 else np.uint16 if top <= 65535 else np.uint32)


def _read_columns(lib: Any, imf: Any, points: Any, wanted: dict[str, np.dtype], i: int, path: str
                  ) -> dict[str, np.ndarray]:
    """The wanted fields of all the scan's records, read CHUNK records at a time."""
    count = points.childCount()
    out = {name: np.empty(count, dtype) for name, dtype in wanted.items()}
    capacity = max(1, min(count, CHUNK))
    chunks = {name: np.empty(capacity, dtype) for name, dtype in wanted.items()}
    done = 0
    try:
        buffers = lib.VectorSourceDestBuffer()
        for name, array in chunks.items():
            buffers.append(lib.SourceDestBuffer(imf, name, array, capacity, True, True))
        reader = points.reader(buffers)
        try:
            while done < count:
                got = reader.read()
                if got == 0:
                    break
                for name, array in chunks.items():
                    out[name][done:done + got] = array[:got]
                done += got
        finally:
            reader.close()
    except lib.E57Exception as exc:
        raise InputError(f"scan {i}: corrupt or truncated point data ({_first_line(exc)})", path) from None
    if done != count:
        raise InputError(f"scan {i}: point data ends after {done} of its {count} points (truncated)", path)
    return out


def _intensity_limits(lib: Any, scan: Any, node: Any) -> tuple[float, float]:
    """The scan's intensityLimits, else the intensity field's own bounds (the E57 standard's fallback)."""
    if scan.isDefined("intensityLimits"):
        limits = scan["intensityLimits"]
        if limits.isDefined("intensityMinimum") and limits.isDefined("intensityMaximum"):
            return _number(lib, limits["intensityMinimum"]), _number(lib, limits["intensityMaximum"])
    if isinstance(node, lib.ScaledIntegerNode):
        return (node.scale() * node.minimum() + node.offset(), node.scale() * node.maximum() + node.offset())
    return float(node.minimum()), float(node.maximum())


def _read_raw(path: str, i: int) -> tuple[dict[str, np.ndarray], tuple[str, ...], str, tuple[float, float] | None]:
    """(scan i's columns, its coordinate fields, its invalid-state field, its intensity limits or None)."""
    with _image(path) as (lib, imf):
        try:
            scans = _scan_nodes(imf, path)
            if not 0 <= i < len(scans):
                raise InputError(f"scan {i} does not exist: the file holds {len(scans)} scan(s)", path)
            scan = scans[i]
            points, fields = _prototype(lib, scan, i, path)
            if points.childCount() == 0:
                raise InputError(f"scan {i} holds no points", path)
            coords = CARTESIAN if set(CARTESIAN) <= fields.keys() else SPHERICAL
            state = "cartesianInvalidState" if coords is CARTESIAN else "sphericalInvalidState"
            wanted = {name: np.dtype(np.float64) for name in coords}
            if state in fields:
                wanted[state] = np.dtype(np.int8)
            if "intensity" in fields:
                wanted["intensity"] = np.dtype(np.float64)
            if set(COLOURS) <= fields.keys():
                wanted.update({name: _colour_dtype(lib, fields[name]) for name in COLOURS})
            limits = _intensity_limits(lib, scan, fields["intensity"]) if "intensity" in fields else None
            return _read_columns(lib, imf, points, wanted, i, path), coords, state, limits
        except lib.E57Exception as exc:
            raise InputError(f"scan {i}: corrupt E57 scan ({_first_line(exc)})", path) from None


def read_e57_scan(path: str, i: int) -> Scan:
    """Scan i of an E57 file in its own frame: valid points (float64), intensity normalised to the file's
    limits (float32), colour as stored, the scanner at the origin, invalid points counted in `dropped`."""
    columns, coords, state, limits = _read_raw(path, i)
    xyz = np.stack([columns[name] for name in coords], axis=1)
    if coords is SPHERICAL:  # range, azimuth, elevation (radians) -> x, y, z
        r, az, el = xyz.T
        xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)
    keep = columns[state] == 0 if state in columns else np.ones(len(xyz), bool)
    dropped = int(len(keep) - keep.sum())
    if not keep.any():
        raise InputError(f"scan {i}: all {len(keep)} points are marked invalid ({state} != 0)", path)
    attributes: dict[str, np.ndarray] = {}
    if limits is not None:
        low, high = limits
        values = columns["intensity"]
        if np.isfinite([low, high]).all() and high > low:
            values = (values - low) / (high - low)
        attributes["intensity"] = values.astype(np.float32)
    for name, short in COLOURS.items():
        if name in columns:
            attributes[short] = columns[name]
    name = f"{path}#{i}"
    scan_out = Scan(xyz[keep], {k: v[keep] for k, v in attributes.items()}, np.zeros((1, 3)), name,
                    {INVALID: dropped} if dropped else {})
    return finalize(scan_out, name)


def open_e57(path: str, topic: str | None) -> Sequence:
    """An E57 file as a sequence: frame i is scan i ("FILE.e57#i") with its pose; every scan's pose and
    coordinate fields are checked here, so a bad scan anywhere in the file is named before any work starts."""
    if topic is not None:
        raise InputError("--topic applies to ROS bags (.bag, .mcap, .db3 or a ROS 2 bag folder), not to an E57 "
                         "file", path)
    with _image(path) as (lib, imf):
        try:
            scans = _scan_nodes(imf, path)
            poses = []
            for i, scan in enumerate(scans):
                _prototype(lib, scan, i, path)
                poses.append(scan_pose(lib, scan, i, path))
        except lib.E57Exception as exc:
            raise InputError(f"corrupt E57 file ({_first_line(exc)})", path) from None

    def reader(i: int) -> Scan:
        try:
            return read_e57_scan(path, i)
        except MemoryError:
            raise InputError(f"scan {i} is too large to read into memory", path) from None

    return Sequence("e57", path, tuple(f"{path}#{i}" for i in range(len(scans))), tuple(poses), "e57", reader)

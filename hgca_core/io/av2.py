"""Argoverse 2 sensor logs: lidar sweeps (.feather), the log's ego poses and the lidar extrinsics.

Conventions of the AV2 sensor dataset (argoverse/av2-api): a sweep `sensors/lidar/<timestamp_ns>.feather`
holds x, y, z (already in the ego-vehicle frame), intensity, laser_number and offset_ns; it merges two
stacked VLP-32C, lasers 0-31 from `up_lidar` and 32-63 from `down_lidar`. `city_SE3_egovehicle.feather`
gives the ego->city pose per timestamp (qw, qx, qy, qz, tx_m, ty_m, tz_m) and
`calibration/egovehicle_SE3_sensor.feather` the sensor->ego poses. City coordinates are km-scale, so every
pose stays float64. pyarrow is imported only when a feather file is read.
"""
from __future__ import annotations

import os

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.georef import check_bound
from hgca_core.io.poses import validate_pose
from hgca_core.io.scan import Scan

LIDARS = ("up_lidar", "down_lidar")  # laser_number // 32 indexes this tuple
POSE_COLUMNS = ("qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")
SWEEP_COLUMNS = ("x", "y", "z")
CALIBRATION = os.path.join("calibration", "egovehicle_SE3_sensor.feather")
EGO_POSES = "city_SE3_egovehicle.feather"


def read_table(path: str, columns: tuple[str, ...], what: str) -> dict[str, np.ndarray]:
    """The named columns of a feather file as numpy arrays; a missing column or a bad file is an InputError."""
    try:
        import pyarrow.feather as feather
    except ImportError as exc:
        raise InputError(f"reading Argoverse 2 .feather files needs pyarrow (pip install 'hgca[real]'): {exc}",
                         path) from None
    if not os.path.isfile(path):
        raise InputError(f"{what} not found", path)
    try:
        table = feather.read_table(path)
    except Exception as exc:  # noqa: BLE001 - any Arrow failure is a corrupt file
        raise InputError(f"corrupt or truncated {what} ({type(exc).__name__}: {exc})", path) from None
    names = list(table.column_names)
    repeated = sorted({c for c in names if names.count(c) > 1})
    if repeated:
        raise InputError(f"{what} has column {repeated[0]!r} {names.count(repeated[0])} times: which one holds "
                         "the values is unknown", path)
    missing = [c for c in columns if c not in table.column_names]
    if missing:
        raise InputError(f"{what} lacks column(s) {', '.join(missing)} (has {', '.join(table.column_names)})",
                         path)
    return {name: table.column(name).to_numpy(zero_copy_only=False) for name in table.column_names}


def numeric(table: dict[str, np.ndarray], name: str, what: str, path: str, integral: bool = False) -> np.ndarray:
    """Column `name` as numbers, or InputError: strings or objects parsed as numbers would be a silent guess."""
    values = table[name]
    if values.dtype.kind not in ("iu" if integral else "iuf") and not (integral and values.dtype.kind == "f"):
        kind = "strings" if values.dtype.kind in "OSU" else f"values of type {values.dtype}"
        raise InputError(f"{what} column {name!r} holds {kind}, not numbers", path)
    if integral and values.dtype.kind == "f":
        bad = ~np.isfinite(values) | (values != np.round(values))
        if bad.any():
            raise InputError(f"{what} column {name!r} must hold whole numbers; row {int(np.flatnonzero(bad)[0])} "
                             f"holds {values[np.flatnonzero(bad)[0]]}", path)
    return values


def quat_pose(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 float64 pose from a unit quaternion (w, x, y, z) and a translation."""
    w, x, y, z = (np.asarray(q, dtype=np.float64) / np.linalg.norm(q)).tolist()
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = np.asarray(t, dtype=np.float64)
    return m


def log_root(sweep_path: str) -> str:
    """The log folder of `<log>/sensors/lidar/<ts>.feather`."""
    return os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(sweep_path))))


def lidar_origins(calibration_path: str) -> np.ndarray:
    """(2, 3) ego-frame positions of up_lidar and down_lidar from an egovehicle_SE3_sensor table."""
    table = read_table(calibration_path, ("sensor_name", *POSE_COLUMNS), "AV2 calibration table")
    names = [str(n) for n in table["sensor_name"]]
    columns = [numeric(table, c, "AV2 calibration table", calibration_path) for c in ("tx_m", "ty_m", "tz_m")]
    rows = []
    for lidar in LIDARS:
        if lidar not in names:
            raise InputError(f"AV2 calibration has no {lidar!r} row (sensors: {', '.join(names)})", calibration_path)
        if names.count(lidar) > 1:
            raise InputError(f"AV2 calibration has {names.count(lidar)} {lidar!r} rows: which one holds is unknown",
                             calibration_path)
        i = names.index(lidar)
        rows.append([c[i] for c in columns])
    origins = np.asarray(rows, dtype=np.float64)
    if not np.isfinite(origins).all():
        raise InputError("AV2 calibration has non-finite lidar positions", calibration_path)
    check_bound(origins, calibration_path, "lidar position")
    return origins


def read_av2_sweep(path: str, calibration: str | None = None) -> Scan:
    """One AV2 lidar sweep in the ego frame. Origins are the two lidars' positions (from `calibration`, else
    the log's own calibration file) with `origin_index` = laser_number // 32 per point; without any
    calibration the origins are unknown (None)."""
    what = "AV2 lidar sweep"
    table = read_table(path, (*SWEEP_COLUMNS, "laser_number"), what)
    pts = np.stack([numeric(table, c, what, path).astype(np.float64) for c in SWEEP_COLUMNS], axis=1)
    laser = numeric(table, "laser_number", what, path, integral=True).astype(np.int64)
    attributes: dict[str, np.ndarray] = {"laser_number": laser.astype(np.uint8)}
    if "intensity" in table:
        attributes["intensity"] = np.asarray(numeric(table, "intensity", what, path))
    if "offset_ns" in table:
        offset_ns = numeric(table, "offset_ns", what, path, integral=True)
        if len(offset_ns) and (offset_ns.min() < np.iinfo(np.int32).min or offset_ns.max() > np.iinfo(np.int32).max):
            raise InputError(f"{what} column 'offset_ns' runs from {offset_ns.min()} to {offset_ns.max()}: beyond "
                             "a sweep's duration", path)
        attributes["offset_ns"] = offset_ns.astype(np.int32)
    if len(laser) and (laser.min() < 0 or laser.max() >= 32 * len(LIDARS)):
        raise InputError(f"laser_number outside 0-63 (found {laser.min()}-{laser.max()}): not an AV2 sweep", path)
    calib = calibration or os.path.join(log_root(path), CALIBRATION)
    origins = None
    if calibration is not None or os.path.isfile(calib):
        origins = lidar_origins(calib)
        attributes["origin_index"] = (laser // 32).astype(np.uint16)
    return Scan(pts, attributes, origins, path)


def sweep_timestamp(path: str) -> int:
    """The sweep's timestamp in ns, from its file name."""
    stem = os.path.basename(path)[: -len(".feather")]
    if not stem.isdigit():
        raise InputError("AV2 lidar sweeps must be named <timestamp_ns>.feather", path)
    return int(stem)


def ego_poses(log: str, timestamps: list[int]) -> list[np.ndarray]:
    """The ego->city pose at each timestamp: an exact row of the log's pose table, else an InputError saying
    whether the table does not reach the timestamp or has no row at it (AV2 logs have one per sweep)."""
    path = os.path.join(log, EGO_POSES)
    what = "AV2 ego pose table"
    table = read_table(path, ("timestamp_ns", *POSE_COLUMNS), what)
    ts = numeric(table, "timestamp_ns", what, path, integral=True).astype(np.int64)
    for c in POSE_COLUMNS:
        numeric(table, c, what, path)
    if len(ts) == 0:
        raise InputError("AV2 ego pose table has no rows", path)
    order = np.argsort(ts, kind="stable")
    ts_sorted = ts[order]
    repeated = np.flatnonzero(ts_sorted[1:] == ts_sorted[:-1])
    if len(repeated):
        stamp = int(ts_sorted[repeated[0]])
        raise InputError(f"AV2 ego pose table has {int((ts == stamp).sum())} rows for timestamp {stamp}: which "
                         "pose holds is unknown", path)
    poses = []
    for stamp in timestamps:
        j = int(np.searchsorted(ts_sorted, stamp))
        if j >= len(ts_sorted) or ts_sorted[j] != stamp:
            if stamp < ts_sorted[0] or stamp > ts_sorted[-1]:
                where = f"it covers {ts_sorted[0]} to {ts_sorted[-1]}"
            else:
                near = ts_sorted[max(0, j - 1): j + 1]
                gap = float(np.min(np.abs(near - stamp))) / 1e6
                where = f"the nearest row is {gap:.3f} ms away"
            raise InputError(f"no ego pose for sweep timestamp {stamp} ({where})", path)
        i = order[j]
        q = np.array([table[c][i] for c in ("qw", "qx", "qy", "qz")], dtype=np.float64)
        t = np.array([table[c][i] for c in ("tx_m", "ty_m", "tz_m")], dtype=np.float64)
        if not (np.isfinite(q).all() and np.isfinite(t).all()) or np.linalg.norm(q) < 1e-9:
            raise InputError(f"ego pose at {stamp} is not a finite unit quaternion and translation", path)
        poses.append(validate_pose(quat_pose(q, t), f"ego pose at {stamp}", path))
    return poses

"""Sensor poses estimated from the scans themselves (LiDAR odometry by KISS-ICP), for recordings that come
without poses: a completion from one sweep is far weaker than from several, and several sweeps need poses.

KISS-ICP (Vizzo et al. 2023, `kiss_icp`, the recordings extra) registers each frame to a local voxel map of the
frames before it, with a constant-velocity prediction, an adaptive correspondence threshold and, when the points
carry per-point times, deskewing. Odometry fails quietly (a corridor, a frame of another place, a gap in the
recording) and a wrong pose misplaces a whole sweep in the completion, so every frame is checked here and a failed
one is an InputError naming the frame (index and name) and what went wrong, never a pose written anyway.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.scan import Scan

MIN_POINTS = 1000          # points a frame needs inside the range window: a 6-dof fit from fewer is not trusted
MAX_SPEED = 40.0           # m/s: faster than any road vehicle a LiDAR rides on (144 km/h)
MAX_TURN = 90.0            # deg/s: a car turning a tight corner does 30-60
PER_FRAME = (8.0, 18.0)    # m, deg per frame when frame times are unknown: the bounds above at 5 Hz (slowest spin)
GAP_FACTOR = 5.0           # a frame interval above 5x the median is a gap (dropped frames, a pause)
MIN_FITNESS = 0.8          # share of a frame's registration points with a map point within FIT_DISTANCE
FIT_DISTANCE = 1.0         # m (or 3 voxels if more): a registered street sweep has 96-99 % of its points this
#                            close to the map, a sweep of another street spliced in 65 % (its ground still fits)
MIN_CONSTRAINT = 0.01      # smallest eigenvalue of the normalised point-to-plane information (see _constraint)
MAX_VOXEL = 0.3           # m: KISS-ICP's max_range / 100, at most this (see `estimate`)
RANGE_QUANTILE = 99.5      # max_range: this percentile of the point ranges, capped at KISS-ICP's default 100 m
NEIGHBOURS = 10            # map points per normal estimate


@dataclass
class Estimate:
    """What `estimate` found: float64 4x4 sensor->world poses (frame 0 = identity), the KISS-ICP settings it
    chose, and per-frame checks (fitness, rmse, constraint) for the poses JSON's "estimated" record."""

    poses: list[np.ndarray]
    settings: dict
    frames: list[dict] = field(default_factory=list)
    version: str = ""

    def record(self) -> dict:
        """The poses JSON's "estimated" record: how these poses were made, so a reader knows they are estimated."""
        return {"method": "kiss-icp", "version": self.version, "settings": self.settings, "frames": self.frames}


def _kiss():
    try:
        import kiss_icp
        from kiss_icp.config import KISSConfig
        from kiss_icp.config.config import DataConfig, MappingConfig
        from kiss_icp.kiss_icp import KissICP
    except ImportError:
        raise InputError("estimating poses needs the recordings extra (pip install 'hgca[recordings]')") from None
    return kiss_icp, KISSConfig, DataConfig, MappingConfig, KissICP


def estimate_poses(scans: list[Scan], times: list[float] | None, names: list[str],
                   progress: Callable[[int, int], None] | None = None) -> list[np.ndarray]:
    """Sensor->world poses of `scans` (each in its own sensor frame, in time order), frame 0 = identity; see
    `estimate` for the settings and the checks."""
    return estimate(scans, times, names, progress).poses


def estimate(scans: list[Scan], times: list[float] | None, names: list[str],
             progress: Callable[[int, int], None] | None = None, voxel_size: float | None = None) -> Estimate:
    """KISS-ICP odometry over `scans` with every frame checked.

    Settings, from the data: max_range = the 99.5th percentile of the first frame's point ranges, at most
    KISS-ICP's default 100 m (points beyond it are few and sparse and only slow the map down); voxel_size =
    max_range / 100 (KISS-ICP's own rule) but at most MAX_VOXEL = 0.3 m: hgca's sequences are short and often
    slow, and a coarse map pulls two nearly equal sweeps toward standing still (on the AV2 test log, whose car
    moves 6.6 cm, 1 m voxels leave 4.8 cm of error, 0.3 m voxels 2.2 cm; on a simulated 19 m drive KISS-ICP's
    own 0.6 m voxels drift 1.3 %, 0.3 m voxels 0.9 %); min_range = 0 (KISS-ICP's default: hgca's readers already drop the returns off the own car
    where a dataset marks them). Deskewing is on when the first frame carries a per-point `time` (seconds):
    KISS-ICP normalises each frame's times to [0, 1] and deskews to the sweep's end, so the pose it returns is
    the sensor's at the end; it is moved back along the frame's motion to the frame's reference time (time 0,
    or the first point's for absolute times). KISS-ICP starts at rest, so frame 0 is deskewed with the motion a
    first look at frames 0 and 1 finds.

    Checks (InputError naming the frame): fewer than MIN_POINTS points in the range window; frame times out of
    order or a gap over GAP_FACTOR x the median interval; a frame-to-frame motion beyond MAX_SPEED / MAX_TURN
    (PER_FRAME without times); fewer than MIN_FITNESS of the frame's points near the map after registration (a
    frame of another place); a degenerate registration (two parallel walls, an empty plain: MIN_CONSTRAINT).
    `progress(i, n)` after each frame.
    """
    kiss_icp, KISSConfig, DataConfig, MappingConfig, KissICP = _kiss()
    n = len(scans)
    if n == 0:
        raise InputError("no frames to estimate poses for")
    if len(names) != n or (times is not None and len(times) != n):
        raise ValueError("scans, names and times must have one entry per frame")
    dts = _check_times(times, names)
    head = scans[0]                   # scans may be a lazy sequence (a bag's frames): each is read when needed
    first = np.linalg.norm(head.points, axis=1)
    max_range = float(min(100.0, max(1.0, np.percentile(first, RANGE_QUANTILE)))) if len(first) else 100.0
    deskew = _stamps(head) is not None
    voxel = min(MAX_VOXEL, max_range / 100.0) if voxel_size is None else float(voxel_size)
    settings = {"max_range": round(max_range, 3), "min_range": 0.0, "voxel_size": round(voxel, 4),
                "deskew": deskew, "max_points_per_voxel": 20, "min_points": MIN_POINTS, "min_fitness": MIN_FITNESS,
                "fit_distance": max(FIT_DISTANCE, round(3.0 * voxel, 4)),
                "min_constraint": MIN_CONSTRAINT,
                "max_motion": ({"m_per_s": MAX_SPEED, "deg_per_s": MAX_TURN} if dts is not None
                               else {"m_per_frame": PER_FRAME[0], "deg_per_frame": PER_FRAME[1]})}
    config = KISSConfig(data=DataConfig(max_range=max_range, min_range=0.0, deskew=deskew),
                        mapping=MappingConfig(voxel_size=voxel, max_points_per_voxel=20))
    odometry = KissICP(config)
    if deskew and n > 1:
        # KISS-ICP starts at rest, so the first sweep enters the map undeskewed (smeared by a frame's motion);
        # a first look at frames 0 and 1 gives the motion to deskew frame 0 with and to predict frame 1 from
        probe = KissICP(config)
        for scan in (head, scans[1]):
            stamps = _stamps(scan)
            probe.register_frame(np.ascontiguousarray(scan.points, dtype=np.float64),
                                 stamps[0] if stamps is not None else np.zeros(0))
        odometry.last_delta = np.asarray(probe.last_delta, dtype=np.float64).copy()
    poses: list[np.ndarray] = []
    frames: list[dict] = []
    previous = np.eye(4)
    for i in range(n):
        scan = head if i == 0 else scans[i]
        where = f"frame {i} of {n}"
        pts = np.ascontiguousarray(scan.points, dtype=np.float64)
        r = np.linalg.norm(pts, axis=1)
        inside = int(((r <= max_range)).sum())
        if inside < MIN_POINTS:
            raise InputError(f"{where} has {inside} point(s) within {max_range:.0f} m of the sensor: odometry needs "
                             f"at least {MIN_POINTS} to place it", names[i])
        stamps = _stamps(scan) if deskew else None
        map_points = odometry.local_map.point_cloud() if i else None
        sigma = float(odometry.adaptive_threshold.get_threshold())
        _, source = odometry.register_frame(pts, stamps[0] if stamps is not None else np.zeros(0))
        end_pose = np.asarray(odometry.last_pose, dtype=np.float64)
        pose = end_pose if stamps is None else _at_fraction(end_pose, odometry.last_delta, stamps[1])
        check = {"file": os.path.basename(names[i])}
        if i:
            check.update(_registration_checks(np.asarray(source), map_points, end_pose, 3.0 * sigma,
                                              max(FIT_DISTANCE, 3.0 * voxel)))
            _check_registration(check, where, names[i])
            _check_motion(previous, pose, None if dts is None else dts[i - 1], where, names[i])
        poses.append(pose)
        frames.append(check)
        previous = pose
        if progress is not None:
            progress(i + 1, n)
    base = np.linalg.inv(poses[0])
    return Estimate([base @ p for p in poses], settings, frames, str(getattr(kiss_icp, "__version__", "")))


def _check_times(times: list[float] | None, names: list[str]) -> np.ndarray | None:
    """Frame intervals (s), after refusing frames out of time order and gaps; None without times."""
    if times is None or len(times) < 2:
        return None
    t = np.asarray(times, dtype=np.float64)
    if not np.isfinite(t).all():
        raise InputError(f"frame {int(np.flatnonzero(~np.isfinite(t))[0])}: its time is not a number",
                         names[int(np.flatnonzero(~np.isfinite(t))[0])])
    dts = np.diff(t)
    bad = np.flatnonzero(dts <= 0)
    if len(bad):
        i = int(bad[0]) + 1
        raise InputError(f"frame {i} of {len(t)} is not later than frame {i - 1} ({t[i]:.6f} s after "
                         f"{t[i - 1]:.6f} s): the frames must be in time order, each once", names[i])
    median = float(np.median(dts))
    gaps = np.flatnonzero(dts > GAP_FACTOR * median)
    if len(gaps):
        i = int(gaps[0]) + 1
        raise InputError(f"frame {i} of {len(t)} comes {dts[i - 1]:.3f} s after frame {i - 1}, over {GAP_FACTOR:g}x "
                         f"the median frame interval ({median:.3f} s): a gap in the recording breaks odometry; "
                         "estimate the parts on either side separately (--frames)", names[i])
    return dts


def _stamps(scan: Scan) -> tuple[np.ndarray, float] | None:
    """The frame's per-point times normalised to [0, 1] as KISS-ICP's deskewing reads them, and the fraction at
    the frame's reference time (0 s for times relative to the frame, the first point's for absolute ones); None
    without usable times."""
    t = scan.attributes.get("time")
    if t is None or len(t) != len(scan.points) or not np.issubdtype(np.asarray(t).dtype, np.number):
        return None
    t = np.asarray(t, dtype=np.float64)
    if not np.isfinite(t).all():
        return None
    lo, hi = float(t.min()), float(t.max())
    if not hi - lo > 0 or hi - lo > 1.0:          # all equal (nothing to deskew), or not one sweep's seconds
        return None
    ref = 0.0 if lo - 1.0 <= 0.0 <= hi + 1.0 else lo
    return (t - lo) / (hi - lo), float(np.clip((ref - lo) / (hi - lo), 0.0, 1.0))


def _at_fraction(end_pose: np.ndarray, delta: np.ndarray, s: float) -> np.ndarray:
    """The sensor pose at fraction `s` of the sweep, from its pose at the end and the motion over one frame
    (KISS-ICP's deskew model: T(s) = T_end exp((s - 1) log(delta)))."""
    if s >= 1.0:
        return end_pose
    from scipy.linalg import expm, logm

    log = np.real(logm(np.asarray(delta, dtype=np.float64)))
    out = end_pose @ np.real(expm((s - 1.0) * log))
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def _registration_checks(source: np.ndarray, map_points: np.ndarray | None, pose: np.ndarray,
                         threshold: float, fit_distance: float) -> dict:
    """Fitness (share of registration points with a map point within `fit_distance`), the rmse (m) of the
    correspondences within the ICP's `threshold`, and how well they pin down all six degrees of freedom
    (`_constraint`)."""
    from hgca_core.geometry.nearest import PointIndex

    if map_points is None or len(map_points) < NEIGHBOURS or len(source) == 0:
        return {"fitness": 0.0, "fit_m": round(fit_distance, 3), "rmse_m": None, "constraint": 0.0}
    world = source @ pose[:3, :3].T + pose[:3, 3]
    tree = PointIndex(map_points)
    dist, idx = tree.nearest(world, upper=threshold)
    hit = np.isfinite(dist)
    fitness = float((dist <= fit_distance).mean())
    base = {"fitness": round(fitness, 4), "fit_m": round(fit_distance, 3)}
    if hit.sum() < 6:
        return {**base, "rmse_m": None, "constraint": 0.0}
    near = tree.k_nearest(map_points[idx[hit]], NEIGHBOURS)
    nb = map_points[near]                                   # (M, k, 3)
    centred = nb - nb.mean(axis=1, keepdims=True)
    _, vecs = np.linalg.eigh(np.einsum("mki,mkj->mij", centred, centred))
    normals = vecs[:, :, 0]
    return {**base, "rmse_m": round(float(np.sqrt(np.mean(dist[hit] ** 2))), 4),
            "constraint": round(_constraint(world[hit] - pose[:3, 3], normals), 5)}


def _constraint(points: np.ndarray, normals: np.ndarray) -> float:
    """Smallest eigenvalue of the point-to-plane information of the correspondences, normalised: rows
    [n, (p / L) x n] (L the median range, so rotations count in the same units as translations), H = J^T J / M.
    A direction no surface faces (along two parallel walls, up a featureless plain) gives ~0; a street with
    kerbs, cars and poles gives a few hundredths or more."""
    scale = float(np.median(np.linalg.norm(points, axis=1))) or 1.0
    jac = np.concatenate([normals, np.cross(points / scale, normals)], axis=1)
    info = jac.T @ jac / len(jac)
    return float(np.linalg.eigvalsh(info)[0])


def _check_registration(check: dict, where: str, name: str) -> None:
    if check["fitness"] < MIN_FITNESS:
        raise InputError(f"{where} does not fit the frames before it: only {check['fitness']:.0%} of its points "
                         f"lie within {check['fit_m']:g} m of them after registration (at least {MIN_FITNESS:.0%} "
                         "needed): a frame of another place, or a view that changed completely", name)
    if check["constraint"] < MIN_CONSTRAINT:
        raise InputError(f"{where}: the registration is degenerate (constraint {check['constraint']:.4f} < "
                         f"{MIN_CONSTRAINT}): the surfaces it sees leave a direction of motion unmeasured (a "
                         "corridor of parallel walls, an open plain), so its pose along it is a guess", name)


def _check_motion(previous: np.ndarray, pose: np.ndarray, dt: float | None, where: str, name: str) -> None:
    delta = np.linalg.inv(previous) @ pose
    metres = float(np.linalg.norm(delta[:3, 3]))
    degrees = float(np.degrees(np.arccos(np.clip((np.trace(delta[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))
    if dt is not None:
        if metres > MAX_SPEED * dt or degrees > MAX_TURN * dt:
            raise InputError(f"{where} jumps {metres:.2f} m and {degrees:.1f} deg in {dt:.3f} s from the frame "
                             f"before ({metres / dt:.1f} m/s, {degrees / dt:.0f} deg/s; at most {MAX_SPEED:g} m/s "
                             f"and {MAX_TURN:g} deg/s): a failed registration or a frame of another place", name)
    elif metres > PER_FRAME[0] or degrees > PER_FRAME[1]:
        raise InputError(f"{where} jumps {metres:.2f} m and {degrees:.1f} deg from the frame before (at most "
                         f"{PER_FRAME[0]:g} m and {PER_FRAME[1]:g} deg per frame without frame times): a failed "
                         "registration or a frame of another place", name)


_STAMP = re.compile(r"(\d{13,19})(?=\D*$)")


def name_time(name: str) -> float | None:
    """A frame's time (s) from a timestamp ending its file name (13 digits: ms, 16: us, 18-19: ns; e.g. an
    Argoverse 2 sweep `315966265259836000.feather`, a nuScenes `..._LIDAR_TOP__1532402927647951.pcd.bin`), or
    None."""
    m = _STAMP.search(os.path.basename(name))
    scale = {13: 1e3, 16: 1e6, 18: 1e9, 19: 1e9}.get(len(m.group(1))) if m else None
    return None if scale is None else int(m.group(1)) / scale


def frame_times(names: list[str], root: str | None = None) -> list[float] | None:
    """Frame times (s) where the recording says them: KITTI's times.txt beside velodyne/, else timestamps in
    every frame's name; None when they are unknown (the motion bounds are then per frame)."""
    if root is not None and os.path.isfile(os.path.join(root, "times.txt")):
        try:
            table = [float(v) for v in open(os.path.join(root, "times.txt"), encoding="utf-8").read().split()]
        except ValueError:
            table = []
        numbers = [os.path.basename(n)[:-4] for n in names]
        if table and all(k.isdigit() and int(k) < len(table) for k in numbers):
            return [table[int(k)] for k in numbers]
    found = [name_time(n) for n in names]
    return None if any(t is None for t in found) else [float(t) for t in found]  # type: ignore[arg-type]

"""High LiDAR ReSim (paper, App. "Evaluation Metric"): re-scan the completion from the evaluation poses
with the 128-beam, (-30, 30) degree LiDAR and compare with the same sensor's scan of the ground truth.

Every representation is scored as a mesh by the same ray caster; voxel outputs (the input row, GCA, hGCA's
20 cm and 10 cm cells) are all meshed by `hgca_core.meshing.voxel_mesh.voxel_mesh`, the mesh the product
ships (the paper does not say how it meshes voxels for ReSim).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import trimesh

from hgca_core.errors import InputError
from hgca_core.geometry.raycast import EVAL128, Sensor, cast, make_intersector
from hgca_core.metrics.chamfer import as_points, chamfer_or_penalty


def crop_to_box(points: np.ndarray, size: Sequence[float] | np.ndarray | None) -> np.ndarray:
    """Points inside the region box [0, size) (region frame); all of them when size is None."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if size is None:
        return p
    s = np.asarray(size, dtype=np.float64).reshape(3)
    return p[np.all((p >= 0) & (p < s), axis=1)]


def _check_poses(poses: np.ndarray) -> np.ndarray:
    P = np.asarray(poses, dtype=np.float64)
    if P.ndim == 2:
        P = P[None]
    if P.ndim != 3 or P.shape[1:] != (4, 4):
        raise InputError(f"poses must be (P, 4, 4) sensor->region matrices, got shape {P.shape}")
    if not np.all(np.isfinite(P)):
        raise InputError("poses hold non-finite numbers")
    return P


def default_sensor(sensor: Sensor | None = None) -> Sensor:
    """`sensor`, or the paper's evaluation LiDAR (`hgca_core.geometry.raycast.EVAL128`) when None."""
    if sensor is not None:
        return sensor
    return EVAL128


def resim_scans(mesh: trimesh.Trimesh, poses: np.ndarray, sensor: Sensor | None = None,
                region_size: Sequence[float] | np.ndarray | None = None) -> list[np.ndarray]:
    """Noise-free scans of `mesh` from each pose (region frame), cropped to [0, region_size) when given.

    A mesh without faces yields empty scans rather than an error: an empty completion is a result to score.
    """
    P, sen = _check_poses(poses), default_sensor(sensor)
    if mesh is None or len(mesh.faces) == 0:
        return [np.zeros((0, 3)) for _ in P]
    target = make_intersector(mesh)                 # one BVH, reused for every pose
    return [crop_to_box(cast(target, pose, sen), region_size) for pose in P]


def resim_cd_per_pose(pred_scans: Sequence[np.ndarray], gt_scans: Sequence[np.ndarray], penalty: float,
                      region_size: Sequence[float] | np.ndarray | None = None) -> np.ndarray:
    """Chamfer distance per pose between re-simulated and ground-truth scans (both cropped to the region)."""
    if len(pred_scans) != len(gt_scans):
        raise InputError(f"{len(pred_scans)} re-simulated scans but {len(gt_scans)} ground-truth scans")
    return np.array([chamfer_or_penalty(crop_to_box(as_points(p, "re-simulated scan", True), region_size),
                                        crop_to_box(as_points(g, "ground-truth scan", True), region_size), penalty)
                     for p, g in zip(pred_scans, gt_scans)], dtype=np.float64)


def resim_cd(mesh: trimesh.Trimesh, gt_scans: Sequence[np.ndarray], poses: np.ndarray,
             sensor: Sensor | None = None, region_size: Sequence[float] | np.ndarray | None = None) -> float:
    """High LiDAR ReSim CD in metres: mean over poses of CD(GT scan, scan of the completion), paper's CD_ReSim.

    `sensor` defaults to `hgca_core.geometry.raycast.EVAL128`. With `region_size`, both scans are cropped to the
    region box [0, size), so geometry outside the region of interest never counts.

    Empty re-simulation penalty: when the completion returns no point inside the region from a pose (no
    faces, or nothing in the beams), that pose scores `sensor.max_range` metres, as if every ground-truth
    point's nearest re-simulated point were at the limit of what the sensor can report. That is larger
    than any real completion scores, finite, and keeps averages over a dataset meaningful. A pose whose
    ground-truth scan is also empty scores 0.
    """
    P, sen = _check_poses(poses), default_sensor(sensor)
    if len(gt_scans) != len(P):
        raise InputError(f"{len(P)} poses but {len(gt_scans)} ground-truth scans")
    pred = resim_scans(mesh, P, sen, region_size)
    return float(resim_cd_per_pose(pred, gt_scans, sen.max_range, region_size).mean())

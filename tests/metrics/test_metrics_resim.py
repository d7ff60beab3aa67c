"""High LiDAR ReSim and the full per-sample evaluation, against scenes whose answers are known."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from hgca_core.geometry import raycast as lidar
from hgca_core.geometry.voxel import voxelize
from hgca_core.meshing.voxel_mesh import voxel_mesh
from hgca_core.metrics.evaluate import evaluate_sample
from hgca_core.metrics.iou import iou
from hgca_core.metrics.resim import resim_cd, resim_scans
from hgca_core.metrics.surface import sample_surface

SIZE = np.array([20.0, 20.0, 8.0])                  # region box [0, SIZE) in the region frame
SENSOR = lidar.Sensor(np.linspace(-30.0, 30.0, 64), 1400, 75.0)   # EVAL128's field of view, fewer rays


def _pose(x: float, y: float, z: float) -> np.ndarray:
    p = np.eye(4)
    p[:3, 3] = (x, y, z)
    return p


POSES = np.stack([_pose(2.0, 10.0, 2.0), _pose(6.0, 4.0, 2.0)])


def _quad(corners: list[tuple[float, float, float]]) -> trimesh.Trimesh:
    return trimesh.Trimesh(np.array(corners, dtype=np.float64), np.array([[0, 1, 2], [0, 2, 3]]))


def _wall(x: float) -> trimesh.Trimesh:
    """The plane x = `x`, larger than the region in y and z, so the region crop sets its extent."""
    return _quad([(x, -4.0, 0.0), (x, 24.0, 0.0), (x, 24.0, 10.0), (x, -4.0, 10.0)])


def _scene(wall_x: float = 12.0, car: bool = True) -> trimesh.Trimesh:
    """Ground at z = 1 m, a wall, and a parked "car" on the street."""
    parts = [_quad([(-2.0, -2.0, 1.0), (22.0, -2.0, 1.0), (22.0, 22.0, 1.0), (-2.0, 22.0, 1.0)]), _wall(wall_x)]
    if car:
        parts.append(trimesh.creation.box(extents=(4.0, 1.8, 1.5),
                                          transform=trimesh.transformations.translation_matrix((8.0, 14.0, 1.75))))
    return trimesh.util.concatenate(parts)


def _gt_scans(mesh: trimesh.Trimesh) -> list[np.ndarray]:
    return resim_scans(mesh, POSES, SENSOR, SIZE)


def test_resim_of_the_ground_truth_itself_is_zero() -> None:
    gt = _scene()
    scans = [lidar.cast(gt, p, SENSOR) for p in POSES]     # uncropped GT scans: resim_cd crops both sides
    assert min(len(s) for s in scans) > 1000
    assert resim_cd(gt, scans, POSES, SENSOR, region_size=SIZE) == pytest.approx(0.0, abs=1e-9)


def test_resim_of_a_shifted_wall_is_the_shift() -> None:
    d = 0.5
    gt_scans = _gt_scans(_wall(12.0))
    cd = resim_cd(_wall(12.0 + d), gt_scans, POSES, SENSOR, region_size=SIZE)
    assert cd == pytest.approx(d, abs=0.04)
    assert cd >= d - 1e-6                                   # hits on two planes d apart are never closer


def test_geometry_outside_the_region_is_not_scored() -> None:
    gt = _scene()
    extra = trimesh.creation.box(extents=(2.0, 2.0, 2.0),
                                 transform=trimesh.transformations.translation_matrix((-5.0, 10.0, 2.0)))
    scored = resim_cd(trimesh.util.concatenate([gt, extra]), _gt_scans(gt), POSES, SENSOR, region_size=SIZE)
    assert scored == pytest.approx(0.0, abs=1e-9)
    unscored = resim_cd(trimesh.util.concatenate([gt, extra]), _gt_scans(gt), POSES, SENSOR)
    assert unscored > 0.01                                  # without the crop, outside geometry counts


def test_empty_resimulation_gets_the_documented_penalty() -> None:
    gt_scans = _gt_scans(_scene())
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    assert resim_cd(empty, gt_scans, POSES, SENSOR, SIZE) == SENSOR.max_range
    far = trimesh.creation.box(extents=(1, 1, 1), transform=trimesh.transformations.translation_matrix((500, 0, 0)))
    assert resim_cd(far, gt_scans, POSES, SENSOR, SIZE) == SENSOR.max_range


def test_voxelised_ground_truth_resimulates_within_a_voxel() -> None:
    gt = _scene()
    cells = voxelize(sample_surface(gt, 0.05, seed=1), 0.2, SIZE)
    cd = resim_cd(voxel_mesh(cells, 0.2), _gt_scans(gt), POSES, SENSOR, SIZE)
    # a cell's faces lie within one 20 cm cell of the surface inside it (the ground at z = 1 m sits in the
    # cell spanning [0.95, 1.15), whose top face is what the LiDAR sees), so 0 < CD < 0.2
    assert 0.0 < cd < 0.2


def test_evaluate_sample_known_answers() -> None:
    gt = _scene()
    shifted = _scene(wall_x=12.5, car=False)
    gt_surface = sample_surface(gt, 0.05, seed=7)
    gt_occ20 = voxelize(gt_surface, 0.2, SIZE)
    scans = _gt_scans(gt)
    sample = {
        "region": np.array([10.0, 10.0, 4.0, *SIZE, 0.0]), "eval_poses": POSES.astype(np.float32),
        "eval_scan_0": scans[0].astype(np.float32), "eval_scan_1": scans[1].astype(np.float32),
        "gt_occ20": gt_occ20.astype(np.int16), "visible20": gt_occ20.astype(np.int16),
        "gt_surface": gt_surface.astype(np.float32),
        "street_box": np.array([5.0, 12.0, 11.0, 16.0], np.float32), "ground_z": np.float32(1.0),
    }
    r = evaluate_sample(sample, [gt, shifted], sensor=SENSOR)
    cd_shift = resim_cd(shifted, scans, POSES, SENSOR, SIZE)
    assert r["k"] == 2 and cd_shift > 0.1
    assert r["resim_min"] == pytest.approx(0.0, abs=1e-5)   # float32 storage of the GT scans
    assert r["resim_avg"] == pytest.approx(cd_shift / 2, abs=1e-5)
    assert r["tmd"] == pytest.approx(cd_shift, abs=1e-5)    # k = 2: TMD is the CD between the two re-scans
    assert r["iou_per_sample"][0] > 0.95                    # resampled surface, same cells up to corner slivers
    assert r["iou_per_sample"][1] < r["iou_per_sample"][0]
    assert r["street_cd_per_sample"][0] < 0.03              # the car, sampled twice at 5 cm
    assert r["street_cd_per_sample"][1] == pytest.approx(np.hypot(6.0, 4.0))   # no car: the penalty
    assert r["street_tmd"] == pytest.approx(np.hypot(6.0, 4.0))
    # with the methods' own occupancy, IoU is exactly the cell-set IoU
    own = [gt_occ20, gt_occ20[gt_occ20[:, 2] > 5]]
    r2 = evaluate_sample(sample, [gt, gt], occ20=own, sensor=SENSOR)
    assert r2["iou"] == pytest.approx((1.0 + iou(own[1], gt_occ20)) / 2)
    assert r2["resim_avg"] == pytest.approx(0.0, abs=1e-5) and r2["tmd"] == 0.0

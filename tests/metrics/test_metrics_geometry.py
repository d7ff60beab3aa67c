"""Known answers for Street CD, the baselines and the results table."""
from __future__ import annotations

import numpy as np
import pytest

from hgca_core.metrics.baselines import input_baseline, poisson_baseline
from hgca_core.metrics.evaluate import aggregate, format_table
from hgca_core.metrics.street import street_cd, street_points


def test_street_cd_ignores_ground_and_outside_points() -> None:
    rng = np.random.default_rng(0)
    box, gz = (0.0, 0.0, 10.0, 4.0), 1.0
    g = np.arange(0.0, 3.0)                                         # a 1 m lattice "car" above the ground cut
    car = np.stack(np.meshgrid(2 + g, 1 + g[:2], 1.5 + g[:2], indexing="ij"), -1).reshape(-1, 3)
    gt_ground = np.column_stack([rng.uniform(0, 10, (3000, 2)), np.full(3000, gz)])
    pred_ground = np.column_stack([rng.uniform(0, 10, (500, 2)), gz + rng.uniform(-0.1, 0.19, 500)])
    outside = car + [20.0, 0, 0]                                    # an object off the street box
    gt = np.concatenate([car, gt_ground])
    pred = np.concatenate([car, pred_ground, outside])
    assert street_cd(pred, gt, box, gz) == 0.0
    # a car raised by 0.3 m (< half the lattice step, so each point's NN is its own copy) scores exactly 0.3
    assert street_cd(car + [0, 0, 0.3], car, box, gz) == pytest.approx(0.3, abs=1e-12)
    # no car predicted at all: the documented penalty, the box's x/y diagonal
    assert street_cd(pred_ground, gt, box, gz) == pytest.approx(np.hypot(10, 4))
    assert len(street_points(gt, box, gz)) == len(car)


def test_street_cd_on_a_sloped_street_uses_the_ground_grid() -> None:
    """An 8 % grade: with the ground under the sensor only (ground_z), the road uphill counts as street
    objects; with the sample's ground-height grid only the car does."""
    from hgca_core.geometry.region import GROUND_STEP, ground_at

    rng = np.random.default_rng(1)
    box, gz = (0.0, 0.0, 20.0, 6.0), 1.0
    ground = lambda xy: gz + 0.08 * (xy[:, 0] - 10.0)  # noqa: E731  (the sensor stands at x = 10)
    xs = np.arange(0.0, 21.0, GROUND_STEP)
    grid = np.repeat(ground(np.c_[xs, xs])[:, None], 7, axis=1)
    assert np.allclose(ground_at(grid, np.array([[3.3, 2.7], [25.0, 1.0]])), ground(np.array([[3.3, 0], [20.0, 0]])))
    road_xy = rng.uniform([0, 0], [20, 6], (3000, 2))
    road = np.c_[road_xy, ground(road_xy)]
    g = np.arange(0.0, 3.0)
    car = np.stack(np.meshgrid(12 + g, 1 + g[:2], g[:2], indexing="ij"), -1).reshape(-1, 3)
    car[:, 2] += ground(car[:, :2]) + 0.5
    gt = np.concatenate([car, road])
    assert len(street_points(gt, box, gz, ground_grid=grid)) == len(car)
    assert len(street_points(gt, box, gz)) > len(car) + 500                 # the flat cut keeps the uphill road
    assert street_cd(np.concatenate([car, road[:300]]), gt, box, gz, ground_grid=grid) == 0.0


def test_input_baseline_voxelises_like_the_paper() -> None:
    pts = np.array([[0.04, 0.0, 0.0], [0.06, 0.0, 0.0], [0.16, 0.0, 0.0], [0.26, 0.0, 0.0]])
    # round to 10 cm: x cells 0, 1, 2, 3 -> floor by 2: 0, 0, 1, 1
    cells, mesh = input_baseline(pts)
    assert np.array_equal(cells, [[0, 0, 0], [1, 0, 0]])
    # meshed like the pipeline's coarse output: two cube cells, faces on the cell boundaries
    assert np.allclose(mesh.bounds, [[-0.05, -0.05, -0.05], [0.35, 0.15, 0.15]], atol=1e-9)
    assert mesh.is_watertight and len(mesh.faces) == 20 and np.isclose(mesh.volume, 2 * 0.2 ** 3)
    # cropped to the region's 10 cm grid like the pipeline's s^0: a 0.2 m region keeps 10 cm cells 0 and 1
    assert np.array_equal(input_baseline(pts, region_size=(0.2, 0.2, 0.2))[0], [[0, 0, 0]])


def test_poisson_baseline_reconstructs_a_sphere() -> None:
    rng = np.random.default_rng(0)
    p = rng.normal(size=(20_000, 3))
    p = 2.0 * p / np.linalg.norm(p, axis=1, keepdims=True)
    origins = np.array([[5.0, 0, 0], [-5, 0, 0], [0, 5, 0], [0, -5, 0], [0, 0, 5], [0, 0, -5]])
    m = poisson_baseline(p, origins, depth=6)            # 64^3 octree: enough for a 2 m sphere, fast
    r = np.linalg.norm(m.vertices, axis=1)
    assert len(m.faces) > 1000
    assert np.abs(r - 2.0).max() < 0.03
    # normals were oriented towards the outside sensors, so the surface faces outwards
    assert (np.einsum("ij,ij->i", m.vertex_normals, m.vertices) > 0).mean() > 0.99
    # trimming the 10 % lowest-density vertices leaves most of the sphere
    assert m.area > 0.8 * 4 * np.pi * 4


def test_format_table_scales_like_the_paper() -> None:
    rows = {
        "hGCA": {"k": 3, "representation": "implicit", "resim_min": 0.453, "resim_avg": 0.465, "tmd": 0.092,
                 "iou": 0.5217, "street_cd_min": 0.185, "street_cd_avg": 0.202, "street_tmd": 0.051},
        "input": aggregate([{"k": 1, "resim_min": 0.633, "resim_avg": 0.633, "tmd": np.nan, "iou": 0.3443,
                             "street_cd_min": np.nan, "street_cd_avg": np.nan, "street_tmd": np.nan}]),
    }
    table = format_table(rows)
    lines = table.splitlines()
    assert lines[0].startswith("| Method | Representation | ReSim min")
    assert "| hGCA | implicit | 4.53 | 4.65 | 0.92 | 52.17 | 1.85 | 2.02 | 0.51 |" in lines
    assert "| input | - | 6.33 | - | - | 34.43 | - | - | - |" in lines
    no_street = format_table({"input": rows["input"]})
    assert "Street" not in no_street.splitlines()[0]


def test_aggregate_ignores_undefined_values() -> None:
    rows = [{"k": 3, "resim_min": 0.2, "iou": np.nan}, {"k": 3, "resim_min": 0.4, "iou": 0.5}]
    agg = aggregate(rows)
    assert agg["resim_min"] == pytest.approx(0.3) and agg["iou"] == pytest.approx(0.5) and agg["n"] == 2
    assert np.isnan(agg["street_cd_min"])


def test_table_shows_the_spread_over_scenes() -> None:
    """The per-scene values travel with a row; the spread table gives their sample standard deviation in the
    main table's units (IoU 50 and 70 % -> 14.14; ReSim 0.2 and 0.4 m -> 1.41 at the x10 scale)."""
    scenes = [{"k": 3, "resim_min": 0.2, "resim_avg": 0.25, "tmd": 0.05, "iou": 0.5, "street_cd_min": 0.3,
               "street_cd_avg": 0.35, "street_tmd": 0.02},
              {"k": 3, "resim_min": 0.4, "resim_avg": 0.45, "tmd": 0.05, "iou": 0.7, "street_cd_min": np.nan,
               "street_cd_avg": np.nan, "street_tmd": np.nan}]
    row = aggregate(scenes)
    assert row["per_scene"]["iou"] == [0.5, 0.7]
    lines = format_table({"hGCA": {**row, "representation": "20cm^3"}}).splitlines()
    at = lines.index(next(line for line in lines if line.startswith("Spread over scenes")))
    assert lines[at + 2].startswith("| Method | Scenes | ReSim min")
    # ReSim min, avg, TMD, IoU, then Street CD with one defined scene: no spread
    assert lines[at + 4] == "| hGCA | 2 | 1.41 | 1.41 | 0.00 | 14.14 | - | - | - |"
    reused = {k: v for k, v in row.items() if k != "per_scene"}      # rows of files from before: no spread table
    assert not any(line.startswith("Spread") for line in format_table({"old": reused}).splitlines())

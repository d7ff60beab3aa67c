"""`hgca synth`: the files of one scene, poses that reproduce world coordinates, the preview, errors."""
from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from scipy.spatial import cKDTree

from hgca_core.cli import main
from hgca_core.geometry.region import Region
from hgca_core.dataset.samples import KEYS, load_sample


@pytest.fixture(scope="module")
def out_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth_cli")
    saved = sys.argv
    try:
        assert main(["synth", "--seed", "7", "--scans", "3", "--profile", "av2", "--quick", "--no-preview",
                     "--out", str(out)]) == 0
    finally:
        sys.argv = saved
    return out


def test_writes_every_file(out_dir):
    names = {p.name for p in out_dir.iterdir()}
    expected = {"scene_7.npz", "scene_7_poses.json", "scene_7_gt.ply"} | {f"scene_7_scan{i}.ply" for i in range(3)}
    assert expected <= names
    s = load_sample(out_dir / "scene_7.npz")
    meta = json.loads(str(s["meta"]))
    assert set(s) == set(KEYS) and meta["seed"] == 7 and meta["profile"] == "av2" and meta["n_scans"] == 3


def test_poses_json_reproduces_world_coordinates(out_dir):
    from hgca_core.io import read_scans

    doc = json.loads((out_dir / "scene_7_poses.json").read_text())
    assert [e["file"] for e in doc["scans"]] == [f"scene_7_scan{i}.ply" for i in range(3)]
    world = read_scans([str(out_dir / e["file"]) for e in doc["scans"]], poses=str(out_dir / "scene_7_poses.json"))
    s = load_sample(out_dir / "scene_7.npz")
    r = s["region"]
    region = Region(center=r[:3], size=r[3:6], yaw=float(np.radians(r[6])))
    ego = np.asarray(doc["scans"][0]["pose"])
    assert np.allclose(region.local_matrix() @ ego, s["input_poses"][0], atol=1e-4)  # first scan = ego
    # every stored input point (region frame, rounded to 1 mm) is a PLY point moved by its pose
    tree = cKDTree(world.points)
    sample_world = region.to_world(s["input_points"].astype(np.float64))
    d, _ = tree.query(sample_world[:: max(1, len(sample_world) // 5000)])
    assert d.max() < 3e-3
    # and the sensor-frame files are really in the sensor frame: points surround the origin
    from hgca_core.io import read_scan

    scan0 = read_scan(str(out_dir / "scene_7_scan0.ply")).points
    assert np.linalg.norm(np.median(scan0[:, :2], axis=0)) < 15.0 and np.median(scan0[:, 2]) < 0


def test_gt_mesh_is_world_frame_with_labels(out_dir):
    import trimesh
    from plyfile import PlyData

    mesh = trimesh.load(out_dir / "scene_7_gt.ply", process=False)
    ply = PlyData.read(str(out_dir / "scene_7_gt.ply"))
    labels = np.asarray(ply["vertex"]["label"])
    assert len(mesh.faces) > 1000 and set(np.unique(labels)) >= {0, 1, 2}
    doc = json.loads((out_dir / "scene_7_poses.json").read_text())
    ego = np.asarray(doc["scans"][0]["origin"])
    assert np.all(mesh.bounds[0][:2] < ego[:2]) and np.all(mesh.bounds[1][:2] > ego[:2])


def test_preview_png(tmp_path, out_dir):
    from hgca_core.synth.preview import render_preview

    path = render_preview(load_sample(out_dir / "scene_7.npz"), tmp_path / "p.png", max_points=5000)
    data = open(path, "rb").read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 50_000


@pytest.mark.parametrize("argv", [["synth", "--split", "train", "--out", "x"],
                                  ["synth", "--seed", "1", "--count", "3", "--out", "x"],
                                  ["synth", "--seed", "1", "--scans", "0", "--out", "x"],
                                  ["synth", "--split", "val", "--count", "1", "--profile", "av2", "--out", "x"],
                                  ["synth", "--seed", "1", "--first", "5", "--out", "x"],
                                  ["synth", "--split", "train", "--count", "2", "--first", "999999", "--out", "x"],
                                  ["synth", "--split", "train", "--count", "2", "--first", "-1", "--out", "x"],
                                  ["synth", "--seed", "1", "--style", "strip", "--generator", "6", "--out", "x"]])
def test_bad_arguments_exit_2(argv, capsys):
    saved = sys.argv
    try:
        try:
            code = main(argv)
        except SystemExit as exc:   # refused while parsing (a bound of the flag's type)
            code = exc.code
    finally:
        sys.argv = saved
    assert code == 2 and "error" in capsys.readouterr().err

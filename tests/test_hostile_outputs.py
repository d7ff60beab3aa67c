"""Hostile cases of the second campaign about what a completion writes: an output named as a folder, semantics in
each output format, and numbers at the edges. Each failed on the code before its fix."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

import hgca_core
from hgca_core.errors import InputError
from hgca_core.files import output_paths
from hgca_core.io.writers import write_mesh

EXAMPLE = Path(hgca_core.__file__).parent / "examples"


def test_an_output_ending_in_a_separator_is_called_a_folder(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="names a folder"):
        output_paths(str(tmp_path / "out.npz") + "/", 1)
    proc = subprocess.run([sys.executable, "-m", "hgca_core.cli", "complete", str(EXAMPLE / "street_scan0.laz"),
                           "-o", str(tmp_path / "out.npz") + "/", "--stage", "coarse"], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 2 and "names a folder" in proc.stderr and not list(tmp_path.iterdir())


def test_obj_output_keeps_the_classes_as_groups_and_materials(tmp_path: Path) -> None:
    mesh = trimesh.Trimesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float),
                           np.array([[0, 1, 2], [1, 3, 2]]), process=False)
    mesh.face_attributes["label"] = np.array([2, 0], dtype=np.uint8)
    write_mesh(tmp_path / "m.obj", mesh)
    text = (tmp_path / "m.obj").read_text()
    assert "g road\nusemtl road\nf 2 4 3" in text and "g building\nusemtl building\nf 1 2 3" in text
    back = trimesh.load(tmp_path / "m.obj", process=False, force="mesh")
    assert len(back.faces) == 2 and np.allclose(back.bounds, mesh.bounds)   # readers split vertices per group
    plain = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    write_mesh(tmp_path / "p.obj", plain)
    assert "usemtl road" not in (tmp_path / "p.obj").read_text()


def test_a_nuscenes_poses_json_that_is_a_folder_is_named_as_one(tmp_path: Path) -> None:
    from hgca_testdata import require_real

    sweep = require_real(require_real() / "nuscenes_lidar_top_1532402927647951.pcd.bin")
    folder = tmp_path / "nuscenes"
    folder.mkdir()
    for i in range(2):
        (folder / f"n{i}.pcd.bin").write_bytes(sweep.read_bytes())
    (folder / "poses.json").mkdir()
    proc = subprocess.run([sys.executable, "-m", "hgca_core.cli", "read", str(folder), "-o", str(tmp_path / "r.npz")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "poses.json is a folder" in proc.stderr, proc.stderr

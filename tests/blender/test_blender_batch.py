"""Batch mode: `python -m hgca_blender.batch` (bpy module) writes a .blend that bpy opens, and a PNG."""
from __future__ import annotations

import os
import struct
import subprocess
import sys
from pathlib import Path

import bpy
import pytest

from bl_helpers import CORE_PYTHON, NUSCENES, REPO, SMALL_REGION, require_fixture


def run_batch(args: list[str], tmp_path: Path, module: bool = True) -> subprocess.CompletedProcess:
    entry = ["-m", "hgca_blender.batch"] if module else [str(REPO / "hgca_blender" / "batch.py"), "--"]
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "BLENDER_USER_RESOURCES": str(tmp_path / "bl_user")}
    if os.environ.get("PYTHONPATH"):  # a worktree's PYTHONPATH must reach the core the batch starts
        env["PYTHONPATH"] = os.environ["PYTHONPATH"]
    return subprocess.run([sys.executable, *entry, *args], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=400)


def png_size(path: Path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG file"
    return struct.unpack(">II", head[16:24])


def test_batch_completes_saves_and_renders(tmp_path: Path) -> None:
    scan = require_fixture(NUSCENES)
    blend, png = tmp_path / "scene.blend", tmp_path / "preview.png"
    args = [str(scan), "--samples", "2", "--stage", "coarse", "--t1", "2", "--python", CORE_PYTHON,
            "--region", ",".join(map(str, SMALL_REGION)), "--out", str(blend), "--render", str(png),
            "--render-samples", "2"]
    proc = run_batch(args, tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Done: 2 samples" in proc.stdout
    assert png_size(png) == (640, 480)

    bpy.ops.wm.open_mainfile(filepath=str(blend))
    colls = [c for c in bpy.data.collections if c.name.startswith("hGCA ")]
    assert len(colls) == 1 and len(colls[0].objects) == 2
    assert all(len(o.data.polygons) > 0 and "observed_distance" in o.data.attributes for o in colls[0].objects)
    scans = [o for o in bpy.data.objects if o.get("hgca_role") == "scan"]
    assert len(scans) == 1 and len(scans[0].data.vertices) == NUSCENES.stat().st_size // 20
    assert bpy.context.scene.camera is not None


def test_batch_as_blender_script_reports_bad_input(tmp_path: Path) -> None:
    """The `blender --python hgca_blender/batch.py -- ...` entry (script, no package) runs and fails cleanly."""
    proc = run_batch([str(tmp_path / "missing.pcd"), "--python", CORE_PYTHON, "--out", str(tmp_path / "x.blend")],
                     tmp_path, module=False)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "file not found" in proc.stdout and "missing.pcd" in proc.stdout
    assert not (tmp_path / "x.blend").exists()


def test_batch_rejects_bad_region(tmp_path: Path) -> None:
    scan = require_fixture(NUSCENES)
    proc = run_batch([str(scan), "--python", CORE_PYTHON, "--region", "1,2,3", "--out", str(tmp_path / "x.blend")],
                     tmp_path)
    assert proc.returncode == 2 and "region needs 6 or 7 numbers" in proc.stdout
    assert not (tmp_path / "x.blend").exists()


@pytest.fixture(autouse=True)
def _fresh_file_after():
    yield
    bpy.ops.wm.read_homefile(use_empty=True)

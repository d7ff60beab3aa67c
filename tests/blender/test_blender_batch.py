"""Batch mode: `python -m hgca_blender.batch` (bpy module) writes a .blend that bpy opens, and a PNG."""
from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
from pathlib import Path

import bpy
import pytest

from bl_helpers import CORE_PYTHON, NUSCENES, REPO, SMALL_REGION, core_arrays, require_fixture


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
            "--render-samples", "2", "--render-size", "320x200"]
    proc = run_batch(args, tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Done: 2 samples" in proc.stdout
    assert png_size(png) == (320, 200)

    bpy.ops.wm.open_mainfile(filepath=str(blend))
    colls = [c for c in bpy.data.collections if c.name.startswith("hGCA ")]
    assert len(colls) == 1 and len(colls[0].objects) == 2
    assert all(len(o.data.polygons) > 0 and "observed_distance" in o.data.attributes for o in colls[0].objects)
    scans = [o for o in bpy.data.objects if o.get("hgca_role") == "scan"]
    assert len(scans) == 1 and len(scans[0].data.vertices) == len(core_arrays(
        f"from hgca_core.io import read_scan; s = read_scan({str(NUSCENES)!r})", p="s.points")["p"])
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


def test_batch_drive_makes_one_object_per_tile_per_sample(tmp_path: Path) -> None:
    """`--drive DIR`: `hgca drive` on the scans, the tiles' own parts as objects in one collection."""
    sys.path.insert(0, str(REPO / "tests" / "drive"))
    from drive_data import write_drive

    scans, poses = write_drive(tmp_path / "scans", length=30.0, weave=0.0)
    blend, folder = tmp_path / "drive.blend", tmp_path / "drive"
    args = [*map(str, scans), "--poses", str(poses), "--drive", str(folder), "--tile-size", "12.8", "--overlap",
            "3.2", "--samples", "2", "--stage", "coarse", "--t1", "2", "--python", CORE_PYTHON, "--out", str(blend)]
    proc = run_batch(args, tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Done: 3 tiles x 2 sample(s)" in proc.stdout
    assert json.loads((folder / "drive.json").read_text())["status"] == "complete"

    bpy.ops.wm.open_mainfile(filepath=str(blend))
    colls = [c for c in bpy.data.collections if c.name.startswith("hGCA drive ")]
    assert len(colls) == 1
    objs = sorted(colls[0].objects, key=lambda o: (o["hgca_tile"], o["hgca_sample"]))
    assert [(o["hgca_tile"], o["hgca_sample"]) for o in objs] == [(i, k) for i in range(3) for k in range(2)]
    assert all(len(o.data.polygons) > 0 and "observed_distance" in o.data.attributes for o in objs)
    assert [o.hide_render for o in objs] == [False, True] * 3, "only sample 0 shows"
    # the objects are the tiles' own parts: side by side along x, overlapping at most along their cut
    xs = [(min(v.co.x for v in o.data.vertices) + o.location.x, max(v.co.x for v in o.data.vertices) + o.location.x)
          for o in objs[::2]]
    assert all(a[1] < b[0] + 0.5 for a, b in zip(xs, xs[1:]))


def test_batch_script_runs_from_the_installed_extensions_folder(tmp_path: Path) -> None:
    """`blender -b --python <extensions>/hgca/batch.py -- ...`: the folder is `hgca`, there is no `hgca_blender`
    to import, and the working directory is not a checkout."""
    from hgca_blender import build_extension

    scan = require_fixture(NUSCENES)
    folder = build_extension.stage(tmp_path / "extensions" / "user_default" / "hgca")
    blend = tmp_path / "scene.blend"
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "BLENDER_USER_RESOURCES": str(tmp_path / "bl_user")}
    args = [str(scan), "--stage", "coarse", "--t1", "2", "--python", CORE_PYTHON,
            "--region", ",".join(map(str, SMALL_REGION)), "--out", str(blend)]
    proc = subprocess.run([sys.executable, str(folder / "batch.py"), "--", *args], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=400)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Done: 1 sample" in proc.stdout and blend.is_file()


def test_batch_uses_the_core_that_install_core_set(addon, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The documented batch command without --python finds the core Install Core stored: the preference first,
    then the core_env Install Core made in the extension's user folder (no environment variable, no hgca on PATH)."""
    import argparse

    from bl_helpers import addon_module, prefs

    import importlib

    batch = importlib.import_module(f"{addon.__name__}.batch")   # loaded as the installed extension loads it
    installer = addon_module("jobs.installer")
    monkeypatch.delenv("HGCA_PYTHON", raising=False)
    monkeypatch.setenv("PATH", "/usr/bin:/bin")
    prefs().python_path = str(tmp_path / "chosen" / "python")
    assert batch.core_python(argparse.Namespace(python=None)) == str(tmp_path / "chosen" / "python")
    assert batch.core_python(argparse.Namespace(python="/given/python")) == "/given/python"
    prefs().python_path = ""
    import shutil

    env = installer.env_dir()
    assert not env.exists()
    made = env / "bin" / "python"
    made.parent.mkdir(parents=True)
    made.write_text("#!/bin/sh\n")
    try:
        assert batch.core_python(argparse.Namespace(python=None)) == str(made)
    finally:
        shutil.rmtree(env)


def test_batch_options_are_the_cores_settings() -> None:
    """Every setting the panel shows is a batch option with the core's default, choices, bounds and help (made from
    the schema, not typed again); a value out of the core's bounds fails while parsing, naming the setting."""
    from hgca_blender import batch, settings
    from hgca_core.config import addon_schema

    schema = addon_schema()
    parser = batch.build_parser()
    actions = {a.dest: a for a in parser._actions}
    for name, spec in schema["settings"].items():
        action = actions[name]
        assert action.default == spec["default"], name
        assert list(action.choices or spec.get("choices", [])) == spec.get("choices", []), name
        assert schema["help"][name] in action.help, name
    base = [str(REPO / "x.pcd"), "--out", "x.blend"]
    assert parser.parse_args([*base, "--t2", "3", "--tile-size", "12.8"]).t2 == 3
    for flag, bad in (("--samples", "0"), ("--t2", "1001"), ("--workers", "0"), ("--tile-size", "-1")):
        with pytest.raises(SystemExit):
            parser.parse_args([*base, flag, bad])
    assert settings.parse_type("max_faces")("0") == 0          # 0: every triangle, as the core takes it

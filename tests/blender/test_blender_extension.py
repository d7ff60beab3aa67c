"""Packaging and preferences: Blender's builder makes the zip, Blender's installer installs and enables it."""
from __future__ import annotations

import os
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import addon_utils
import bpy
import pytest

from bl_helpers import ADDON, REPO, addon_module, prefs

from hgca_blender import build_extension


def test_manifest_matches_the_package() -> None:
    manifest = build_extension.read_manifest()
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert manifest["id"] == "hgca" and manifest["type"] == "add-on"
    assert manifest["version"] == project["version"]
    assert manifest["blender_version_min"] == "4.2.0" and manifest["schema_version"] == "1.0.0"
    assert set(manifest["permissions"]) == {"files", "network"}  # network: Install Core's package index


def test_zip_builds_installs_and_enables(addon, tmp_path: Path) -> None:
    zip_path = build_extension.build(tmp_path / "dist")
    assert zip_path.name == "hgca-0.1.0.zip"
    names = set(zipfile.ZipFile(zip_path).namelist())
    assert {"blender_manifest.toml", "__init__.py", "jobs/core.py", "jobs/completion.py", "batch.py", "ui/panels.py",
            "scene/__init__.py", "operators/watch.py"} <= names   # the packages, not only the top level
    assert "build_extension.py" not in names and not any("__pycache__" in n for n in names)
    assert {"jobs/install_core.py", "jobs/installer.py", "core/hgca-0.1.0-py3-none-any.whl"} <= names

    # The session's copy registers the same classes: step it aside while the installed one is tested.
    addon_utils.disable(ADDON, default_set=True)
    repo_dir = tmp_path / "installed_repo"
    repo_dir.mkdir()
    repos = bpy.context.preferences.extensions.repos
    repo = repos.new(name="hgca_install", module="hgca_install", custom_directory=str(repo_dir), source="USER")
    installed = "bl_ext.hgca_install.hgca"
    try:
        result = bpy.ops.extensions.package_install_files(filepath=str(zip_path), repo="hgca_install",
                                                          enable_on_install=True)
        assert result == {"FINISHED"}
        assert (repo_dir / "hgca" / "blender_manifest.toml").is_file()
        assert installed in bpy.context.preferences.addons
        assert hasattr(bpy.types.Scene, "hgca") and hasattr(bpy.ops.import_scene, "hgca_lidar")
        assert bpy.context.preferences.addons[installed].preferences.bl_rna.identifier
        assert "LiDAR Scan (hgca)" in _import_menu_labels()
    finally:
        addon_utils.disable(installed, default_set=True)
        repos.remove(repo)
        assert addon_utils.enable(ADDON, default_set=True, handle_error=None) is not None
    assert ADDON in bpy.context.preferences.addons


def _import_menu_labels() -> list[str]:
    """Labels the installed add-on's File > Import entries draw (its menu functions, run on a recorder)."""

    class Recorder:
        def __init__(self) -> None:
            self.items: list[tuple[str, str]] = []

        def operator(self, idname: str, text: str = "", **_kw) -> None:
            self.items.append((idname, text))

    class FakeMenu:
        layout = Recorder()

    for fn in bpy.types.TOPBAR_MT_file_import._dyn_ui_initialize():
        if fn.__module__.startswith("bl_ext.hgca_install."):
            fn(FakeMenu, bpy.context)
    return [text for idname, text in FakeMenu.layout.items if idname == "import_scene.hgca_lidar"]


def test_check_button_reports_the_core_version(addon) -> None:
    assert bpy.ops.hgca.check_python() == {"FINISHED"}
    assert prefs().check_result.startswith("hgca ")
    prefs().python_path = "/nonexistent/python"
    with pytest.raises(RuntimeError, match="not found"):
        bpy.ops.hgca.check_python()
    assert prefs().check_result.startswith("Error")


def test_check_in_the_interface_returns_at_once_and_reports_when_done(addon) -> None:
    """The interface's *Check* runs on a thread: starting it takes well under a second (importing torch and
    loading the weights take 5-10 s), and its answer reaches the preferences and the report list."""
    import time

    installer = addon_module("jobs.installer")
    from bl_helpers import CORE_PYTHON

    t = time.monotonic()
    installer.start_check(CORE_PYTHON)
    started = time.monotonic() - t
    assert started < 1.0, started
    background = addon_module("jobs.background")
    deadline = time.monotonic() + 300
    while (result := background.poll("check")) is None:
        assert time.monotonic() < deadline
        time.sleep(0.2)
    assert not result.startswith("hGCA check failed") and prefs().check_result.startswith("hgca ")
    with pytest.raises(addon_module("jobs.core").CoreError, match="not found"):
        installer.start_check("/nonexistent/python")


def test_python_detection_order(addon, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    preferences = addon_module("preferences")
    monkeypatch.setenv("HGCA_PYTHON", "/opt/core/bin/python")
    assert preferences.detect_python() == "/opt/core/bin/python"
    monkeypatch.delenv("HGCA_PYTHON")

    bindir = tmp_path / "bin"
    bindir.mkdir()
    script = bindir / "hgca"
    script.write_text(f"#!{sys.executable}\nfrom hgca_core.cli import main\n")
    script.chmod(0o755)
    monkeypatch.setenv("PATH", f"{bindir}{os.pathsep}/usr/bin")
    assert preferences.detect_python() == sys.executable

    # pip's trampoline for interpreters whose path is too long for a shebang line
    script.write_text(f"#!/bin/sh\n'''exec' \"{sys.executable}\" \"$0\" \"$@\"\n' '''\n")
    assert preferences.detect_python() == sys.executable

    # no env var, no script: the installed extension has no repo .venv, but this interpreter has hgca_core
    monkeypatch.setenv("PATH", "/usr/bin")
    assert preferences.detect_python() == sys.executable
    prefs().python_path = ""
    assert preferences.core_python() == sys.executable


UNINSTALL_AND_QUIT = """
import sys, tempfile
from pathlib import Path
sys.path.insert(0, sys.argv[1])
import bpy
import addon_utils  # importable once bpy is
from hgca_blender import build_extension
repo_dir = Path(tempfile.mkdtemp())
build_extension.stage(repo_dir / "hgca")
repos = bpy.context.preferences.extensions.repos
repo = repos.new(name="hgca_quit", module="hgca_quit", custom_directory=str(repo_dir), source="USER")
assert addon_utils.enable("bl_ext.hgca_quit.hgca", default_set=True, handle_error=None) is not None
bpy.context.scene.hgca.region_object = None
addon_utils.disable("bl_ext.hgca_quit.hgca", default_set=True)
assert bpy.ops.extensions.package_uninstall(repo_index=list(repos).index(repo), pkg_id="hgca") == {"FINISHED"}
print("uninstalled", flush=True)
"""


def test_uninstall_then_quit_exits_cleanly(tmp_path: Path) -> None:
    """Blender 4.2 crashed on quit (SIGSEGV) after the extension was uninstalled, because the panel's region box
    property had a `poll` callback; enabling, uninstalling and quitting must end with status 0 on every version."""
    env = {**os.environ, "BLENDER_USER_RESOURCES": str(tmp_path / "user")}
    proc = subprocess.run([sys.executable, "-c", UNINSTALL_AND_QUIT, str(REPO)], env=env, cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert "uninstalled" in proc.stdout, proc.stdout + proc.stderr
    assert proc.returncode == 0, f"exit status {proc.returncode}: {proc.stderr[-2000:]}"


def test_zip_without_blender_has_blenders_layout_and_passes_its_validate(tmp_path: Path) -> None:
    """`make extension` on a machine with only Python (no bpy): the zip written without Blender's builder holds the
    same files as Blender's, and Blender's own `validate` (the extensions platform's check) accepts it."""
    plain = build_extension.build(tmp_path / "plain", use_blender=False)
    blender = build_extension.build(tmp_path / "blender", use_blender=True)
    assert sorted(zipfile.ZipFile(plain).namelist()) == sorted(zipfile.ZipFile(blender).namelist())
    assert "Success" in build_extension.validate(plain)
    bad = dict(build_extension.read_manifest(), tagline="Completes scans.")
    with pytest.raises(build_extension.BuildError, match="tagline"):
        build_extension.check_manifest(bad)


def test_make_extension_needs_no_test_venv(tmp_path: Path) -> None:
    """The Makefile's extension target runs with the system's Python alone: it depends on no venv."""
    makefile = (REPO / "Makefile").read_text()
    rule = makefile[makefile.index("\nextension:"):].split("\n\n")[0]
    assert "$(STAMP)" not in rule.split("\n")[1] and "$(BIN)" not in rule and "$(PY) -m hgca_blender.build_extension" in rule

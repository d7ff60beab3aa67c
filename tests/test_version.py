"""One version source: pyproject.toml. `hgca_core.__version__`, `hgca --version`, the installed metadata and the
Blender extension's manifest all say what it says."""
from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
from importlib import metadata
from pathlib import Path

import hgca_core

REPO = Path(__file__).resolve().parents[1]


def _toml(name: str) -> dict:
    return tomllib.loads((REPO / name).read_text())


def test_package_metadata_and_manifest_carry_pyprojects_version():
    version = _toml("pyproject.toml")["project"]["version"]
    assert hgca_core.__version__ == version
    assert metadata.version("hgca") == version
    assert _toml("blender_manifest.toml")["version"] == version
    out = subprocess.run([sys.executable, "-m", "hgca_core.cli", "--version"], capture_output=True, text=True)
    assert out.stdout.strip() == f"hgca {version}"


def test_the_version_is_read_from_pyproject_not_written_in_the_package(tmp_path):
    """A source tree whose pyproject says another version reports that one (no second copy in the code)."""
    shutil.copytree(REPO / "hgca_core", tmp_path / "hgca_core", ignore=shutil.ignore_patterns("weights", "examples",
                                                                                            "__pycache__"))
    text = (REPO / "pyproject.toml").read_text()
    old = _toml("pyproject.toml")["project"]["version"]
    (tmp_path / "pyproject.toml").write_text(text.replace(f'version = "{old}"', 'version = "97.3.1"', 1))
    out = subprocess.run([sys.executable, "-c", "import hgca_core; print(hgca_core.__version__)"], cwd=tmp_path,
                         env={"PYTHONPATH": str(tmp_path), "PATH": "/usr/bin:/bin"}, capture_output=True, text=True)
    assert out.stdout.strip() == "97.3.1", out.stderr

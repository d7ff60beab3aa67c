"""Build the Blender extension zip: `python -m hgca_blender.build_extension --out build/extension`.

The manifest lives at the repository's top level and the code in `hgca_blender/`, so the repository
root never needs an `__init__.py`. This module stages both into one folder (the layout Blender expects:
`blender_manifest.toml` next to `__init__.py`) and hands that folder to Blender's own builder,
`bl_pkg/cli/blender_ext.py build`, which validates the manifest exactly as Blender will when installing.
It runs with any Python 3.11 that has the `bpy` wheel installed (or with `--blender-ext PATH`) and never
imports bpy itself.
"""
from __future__ import annotations

import argparse
import importlib.util
import shutil
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent
REPO_ROOT = PACKAGE_DIR.parent
MANIFEST = REPO_ROOT / "blender_manifest.toml"
# Development-only modules that are not shipped inside the extension.
EXCLUDED = {"build_extension.py"}


class BuildError(RuntimeError):
    """The extension could not be staged or built; the message says why."""


def read_manifest(path: Path = MANIFEST) -> dict:
    """Parsed manifest (used for the zip name and by tests comparing versions)."""
    with open(path, "rb") as fh:
        return tomllib.load(fh)


def package_files(package_dir: Path = PACKAGE_DIR) -> list[Path]:
    """The add-on's source files: every .py module in the package except development tools."""
    return sorted(p for p in package_dir.glob("*.py") if p.name not in EXCLUDED)


def build_wheel(out_dir: Path, source: Path = REPO_ROOT, python: str = sys.executable) -> Path:
    """hgca's wheel (core, shipped weights) built from `source` into `out_dir`, for *Install Core*."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for old in out_dir.glob("hgca-*.whl"):
        old.unlink()
    # the project's setuptools>=77 from this Python when it has it, else in pip's isolated build environment
    has_setuptools = subprocess.run([python, "-c", "import setuptools, sys; "
                                     "sys.exit(int(setuptools.__version__.split('.')[0]) < 77)"],
                                    capture_output=True).returncode == 0
    isolation = ["--no-build-isolation"] if has_setuptools else []
    proc = subprocess.run([python, "-m", "pip", "wheel", "--no-deps", *isolation, "-q",
                           "-w", str(out_dir), str(source)], capture_output=True, text=True)
    wheels = sorted(out_dir.glob("hgca-*.whl"))
    if proc.returncode != 0 or not wheels:
        raise BuildError(f"building hgca's wheel failed (exit {proc.returncode}): {(proc.stdout + proc.stderr)[-2000:]}")
    return wheels[-1]


def stage(dest: Path, manifest: Path = MANIFEST, package_dir: Path = PACKAGE_DIR,
          core_wheel: Path | None = None) -> Path:
    """Copy the manifest and package files into `dest` (emptied first), with hgca's wheel in `core/` when
    given (the extension's *Install Core* installs it); returns `dest`.

    Tests also point a local extension repository at a staged folder, so the add-on they load is
    byte-for-byte what the zip contains.
    """
    if not manifest.is_file():
        raise BuildError(f"manifest not found: {manifest}")
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    shutil.copy2(manifest, dest / "blender_manifest.toml")
    for src in package_files(package_dir):
        shutil.copy2(src, dest / src.name)
    if not (dest / "__init__.py").is_file():
        raise BuildError(f"{package_dir} has no __init__.py")
    if core_wheel is not None:
        (dest / "core").mkdir()
        shutil.copy2(core_wheel, dest / "core" / Path(core_wheel).name)
    return dest


def find_blender_ext() -> Path:
    """Locate Blender's extension builder shipped inside the bpy wheel, without importing bpy."""
    spec = importlib.util.find_spec("bpy")
    roots: list[Path] = []
    if spec is not None:
        if spec.submodule_search_locations:
            roots += [Path(p) for p in spec.submodule_search_locations]
        elif spec.origin:
            roots.append(Path(spec.origin).parent)
    for root in roots:
        hits = sorted(root.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
        if hits:
            return hits[-1]
    raise BuildError("Blender's builder (bl_pkg/cli/blender_ext.py) not found: install the bpy wheel "
                     "or pass --blender-ext PATH")


def _valid_tags_file(blender_ext: Path) -> Path | None:
    """Blender's list of valid tags (a Python file next to the builder's scripts), when present."""
    scripts = blender_ext.parents[3]
    tags = scripts / "modules" / "_bpy_internal" / "extensions" / "tags.py"
    return tags if tags.is_file() else None


def build(out_dir: Path, blender_ext: Path | None = None, python: str = sys.executable) -> Path:
    """Stage and build; returns the path of `<out_dir>/<id>-<version>.zip`."""
    out_dir = Path(out_dir).resolve()
    manifest = read_manifest()
    zip_path = out_dir / f"{manifest['id']}-{manifest['version']}.zip"
    tool = Path(blender_ext) if blender_ext else find_blender_ext()
    out_dir.mkdir(parents=True, exist_ok=True)
    if zip_path.exists():
        zip_path.unlink()
    with tempfile.TemporaryDirectory(prefix="hgca_ext_") as tmp:
        wheel = build_wheel(Path(tmp) / "wheel", python=python)
        staged = stage(Path(tmp) / manifest["id"], core_wheel=wheel)
        cmd = [python, str(tool), "build", "--source-dir", str(staged), "--output-filepath", str(zip_path)]
        tags = _valid_tags_file(tool)
        if tags is not None:
            cmd.append(f"--valid-tags={tags}")
        proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0 or not zip_path.is_file():
        detail = (proc.stdout + proc.stderr).strip()
        raise BuildError(f"Blender's builder failed (exit {proc.returncode}): {detail}")
    return zip_path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hgca_blender.build_extension", description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="build/extension", help="output folder (default build/extension)")
    parser.add_argument("--blender-ext", default=None, help="path to bl_pkg/cli/blender_ext.py (default: from bpy)")
    args = parser.parse_args(argv)
    try:
        zip_path = build(Path(args.out), Path(args.blender_ext) if args.blender_ext else None)
    except BuildError as exc:
        print(f"build_extension: error: {exc}", file=sys.stderr)
        return 2
    print(zip_path)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Build the Blender extension zip: `python -m hgca_blender.build_extension --out build/extension`.

The manifest lives at the repository's top level and the code in `hgca_blender/`, so the repository
root never needs an `__init__.py`. This module stages both into one folder (the layout Blender expects:
`blender_manifest.toml` next to `__init__.py`) and hands that folder to Blender's own builder,
`bl_pkg/cli/blender_ext.py build`, which validates the manifest exactly as Blender will when installing.
Where Blender's builder is not at hand (a plain Python 3.11 with no `bpy` wheel: `make extension` on a fresh
machine, the release workflow), the same zip is written here, files at its root as Blender's builder lays them
out, after the manifest checks Blender applies on install (`check_manifest`); `--validate` then runs Blender's own
`validate` on the zip when bpy is installed. It never imports bpy.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import re
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


SETTINGS_FILE = "core_settings.json"   # the core's settings schema, which the add-on's properties are made from


def core_settings() -> dict:
    """`hgca_core.config.addon_schema()` of this checkout (torch-free: only the config module is imported)."""
    if str(REPO_ROOT) not in sys.path:
        sys.path.insert(0, str(REPO_ROOT))
    from hgca_core.config import addon_schema

    return addon_schema()


class BuildError(RuntimeError):
    """The extension could not be staged or built; the message says why."""


def read_manifest(path: Path = MANIFEST) -> dict:
    """Parsed manifest (used for the zip name and by tests comparing versions)."""
    with open(path, "rb") as fh:
        return tomllib.load(fh)


def package_files(package_dir: Path = PACKAGE_DIR) -> list[Path]:
    """The add-on's source files: every .py module in the package and its subpackages (`scene/`, `jobs/`,
    `operators/`, `ui/`) except development tools, as paths relative to `package_dir`."""
    return sorted(p.relative_to(package_dir) for p in package_dir.rglob("*.py")
                  if p.name not in EXCLUDED and "__pycache__" not in p.parts)


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
    for rel in package_files(package_dir):
        (dest / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(package_dir / rel, dest / rel)
    if not (dest / "__init__.py").is_file():
        raise BuildError(f"{package_dir} has no __init__.py")
    (dest / SETTINGS_FILE).write_text(json.dumps(core_settings(), indent=1, sort_keys=True) + "\n")
    if core_wheel is not None:
        (dest / "core").mkdir()
        shutil.copy2(core_wheel, dest / "core" / Path(core_wheel).name)
    return dest


MANIFEST_KEYS = ("schema_version", "id", "version", "name", "tagline", "maintainer", "type", "blender_version_min",
                 "license")


def check_manifest(manifest: dict) -> None:
    """The checks Blender's installer makes of a manifest's fields (required keys, an identifier for `id`, a
    semantic version, a tagline of at most 64 characters without final punctuation), as a BuildError naming the
    field; Blender's `validate` stays the reference where bpy is installed."""
    missing = [k for k in MANIFEST_KEYS if not manifest.get(k)]
    if missing:
        raise BuildError(f"manifest lacks {', '.join(missing)}")
    if not str(manifest["id"]).isidentifier():
        raise BuildError(f"manifest id must be an identifier, not {manifest['id']!r}")
    for key in ("version", "blender_version_min", "schema_version"):
        if not re.fullmatch(r"\d+\.\d+\.\d+", str(manifest[key])):
            raise BuildError(f"manifest {key} must be MAJOR.MINOR.PATCH, not {manifest[key]!r}")
    tagline = str(manifest["tagline"])
    if len(tagline) > 64 or tagline[-1] in ".!?,;:":
        raise BuildError(f"manifest tagline must be at most 64 characters without final punctuation: {tagline!r}")
    if manifest["type"] not in ("add-on", "theme"):
        raise BuildError(f"manifest type must be add-on or theme, not {manifest['type']!r}")
    if not isinstance(manifest["license"], list) or not all(str(v).startswith("SPDX:") for v in manifest["license"]):
        raise BuildError("manifest license must be a list of SPDX:... identifiers")


def zip_folder(staged: Path, zip_path: Path) -> Path:
    """`staged` as an extension zip: every file at the zip's root, in sorted order (the same bytes for the same
    files, whatever the machine)."""
    import zipfile

    with zipfile.ZipFile(zip_path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(p for p in staged.rglob("*") if p.is_file()):
            info = zipfile.ZipInfo(path.relative_to(staged).as_posix(), date_time=(2024, 1, 1, 0, 0, 0))
            info.compress_type, info.external_attr = zipfile.ZIP_DEFLATED, 0o644 << 16
            zf.writestr(info, path.read_bytes())
    return zip_path


def validate(zip_path: Path, blender_ext: Path | None = None, python: str = sys.executable) -> str:
    """Blender's own `blender_ext.py validate` of a built zip (what the extensions platform runs); its report."""
    tool = Path(blender_ext) if blender_ext else find_blender_ext()
    cmd = [python, str(tool), "validate", str(zip_path)]
    tags = _valid_tags_file(tool)
    if tags is not None:
        cmd.append(f"--valid-tags={tags}")
    proc = subprocess.run(cmd, capture_output=True, text=True)
    report = (proc.stdout + proc.stderr).strip()
    if proc.returncode != 0 or "error" in report.lower():
        raise BuildError(f"Blender's validate refused {zip_path.name} (exit {proc.returncode}): {report}")
    return report


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


def build(out_dir: Path, blender_ext: Path | None = None, python: str = sys.executable,
          use_blender: bool | None = None) -> Path:
    """Stage and build; returns the path of `<out_dir>/<id>-<version>.zip`. `use_blender`: True builds with
    Blender's builder (an error without it), False writes the zip here, None uses Blender's when found."""
    out_dir = Path(out_dir).resolve()
    manifest = read_manifest()
    check_manifest(manifest)
    zip_path = out_dir / f"{manifest['id']}-{manifest['version']}.zip"
    tool = Path(blender_ext) if blender_ext else None
    if tool is None and use_blender is not False:
        try:
            tool = find_blender_ext()
        except BuildError:
            if use_blender:
                raise
    out_dir.mkdir(parents=True, exist_ok=True)
    if zip_path.exists():
        zip_path.unlink()
    with tempfile.TemporaryDirectory(prefix="hgca_ext_") as tmp:
        wheel = build_wheel(Path(tmp) / "wheel", python=python)
        staged = stage(Path(tmp) / manifest["id"], core_wheel=wheel)
        if tool is None:
            return zip_folder(staged, zip_path)
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
    parser.add_argument("--blender-ext", default=None, help="path to bl_pkg/cli/blender_ext.py (default: from bpy, "
                                                            "else the zip is written without Blender)")
    parser.add_argument("--validate", action="store_true",
                        help="then run Blender's own `validate` on the zip (needs bpy or --blender-ext)")
    args = parser.parse_args(argv)
    try:
        tool = Path(args.blender_ext) if args.blender_ext else None
        zip_path = build(Path(args.out), tool)
        if args.validate:
            print(validate(zip_path, tool), file=sys.stderr)
    except BuildError as exc:
        print(f"build_extension: error: {exc}", file=sys.stderr)
        return 2
    print(zip_path)
    return 0


if __name__ == "__main__":
    sys.exit(main())

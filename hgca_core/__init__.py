"""hgca_core: headless hGCA (hierarchical Generative Cellular Automata) for LiDAR scene extrapolation.

`hgca_core.complete_files(scans, out, poses=..., samples=...)` is `hgca complete` as a call (files in, mesh files
out, the CLI's meshes); `hgca_core.complete(points, region=..., config=CompletionConfig(...))` completes arrays
(`hgca_core.pipeline.complete`) and `hgca_core.drive(scans, out, poses=..., config=DriveConfig(...))` that of
`hgca drive` (`hgca_core.tiling.run.drive`); single settings may be given as keywords (`stage="coarse"`). The
configs (`hgca_core.config`) hold every default. All are imported on first use, so `import hgca_core` stays
light (no torch).
"""
import os as _os

# MKL's strict conditional numerical reproducibility: float32 GEMMs give the same bits whatever the thread count
# (without it, MKL splits a GEMM's reduction by thread count, and a weight gradient, or a completion, differs in
# the last bits between 1 and 2 threads). MKL reads the variable at its first call, so it is set here, before
# anything in hgca runs a GEMM; a value the user set wins (tests/test_determinism.py).
_os.environ.setdefault("MKL_CBWR", "AUTO,STRICT")

from hgca_core.errors import HgcaError, InputError  # noqa: E402

def _version() -> str:
    """The version pyproject.toml declares (its one home): the installed distribution's metadata, or, for a source
    tree on sys.path without an install, the pyproject.toml beside the package."""
    from importlib import metadata
    from pathlib import Path

    source = Path(__file__).resolve().parents[1] / "pyproject.toml"
    if source.is_file():                  # a checkout (an editable install too): its own pyproject is the truth
        import tomllib

        project = tomllib.loads(source.read_text()).get("project", {})
        if project.get("name") == "hgca":
            return project["version"]
    try:
        return metadata.version("hgca")
    except metadata.PackageNotFoundError:
        return "0+unknown"


__version__ = _version()

__all__ = ["HgcaError", "InputError", "__version__", "complete", "complete_files", "drive", "Region",
           "CompletionConfig", "DriveConfig"]


def __getattr__(name: str):
    if name == "complete":
        from hgca_core.pipeline import complete

        return complete
    if name == "complete_files":
        from hgca_core.files import complete_files

        return complete_files
    if name == "drive":
        from hgca_core.tiling.run import drive

        return drive
    if name in ("CompletionConfig", "DriveConfig"):
        from hgca_core import config

        return getattr(config, name)
    if name == "Region":
        from hgca_core.geometry.region import Region

        return Region
    raise AttributeError(f"module 'hgca_core' has no attribute {name!r}")

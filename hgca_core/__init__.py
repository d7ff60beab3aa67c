"""hgca_core: headless hGCA (hierarchical Generative Cellular Automata) for LiDAR scene extrapolation.

`hgca_core.complete(points, region=..., samples=..., seed=...)` is the Python API of `hgca complete`
(`hgca_core.pipeline.complete`) and `hgca_core.drive(scans, out, poses=...)` that of `hgca drive`
(`hgca_core.tiling.run.drive`); both are imported on first use, so `import hgca_core` stays light (no torch).
"""
from hgca_core.errors import HgcaError, InputError

__version__ = "0.1.0"

__all__ = ["HgcaError", "InputError", "__version__", "complete", "drive", "Region"]


def __getattr__(name: str):
    if name == "complete":
        from hgca_core.pipeline import complete

        return complete
    if name == "drive":
        from hgca_core.tiling.run import drive

        return drive
    if name == "Region":
        from hgca_core.geometry.region import Region

        return Region
    raise AttributeError(f"module 'hgca_core' has no attribute {name!r}")

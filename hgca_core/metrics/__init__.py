"""The paper's evaluation metrics (High LiDAR ReSim, IoU, Street CD, TMD) and the simple baselines.

The light ones load with the package; the evaluation driver, ReSim and Street CD (meshes through trimesh, the LiDAR
simulator, Open3D for the Poisson baseline) load when first used (PEP 562), so that training's validation IoU runs
where only torch, numpy and scipy are installed (a GPU machine).
"""
from importlib import import_module

from hgca_core.metrics.chamfer import chamfer, chamfer_or_penalty, directed_chamfer
from hgca_core.metrics.iou import iou
from hgca_core.metrics.tmd import tmd

_LAZY = {"aggregate": "evaluate", "evaluate_sample": "evaluate", "format_table": "evaluate",
         "resim_cd": "resim", "resim_scans": "resim", "street_cd": "street"}
__all__ = ["chamfer", "chamfer_or_penalty", "directed_chamfer", "iou", "tmd", *_LAZY]


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(import_module(f"{__name__}.{_LAZY[name]}"), name)

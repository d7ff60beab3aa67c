"""The paper's evaluation metrics (High LiDAR ReSim, IoU, Street CD, TMD) and the simple baselines.

Open3D (Poisson baseline) and the LiDAR simulator (ReSim) are imported only when used.
"""
from hgca_core.metrics.chamfer import chamfer, chamfer_or_penalty, directed_chamfer
from hgca_core.metrics.evaluate import aggregate, evaluate_sample, format_table
from hgca_core.metrics.iou import iou
from hgca_core.metrics.resim import resim_cd, resim_scans
from hgca_core.metrics.street import street_cd
from hgca_core.metrics.tmd import tmd

__all__ = ["chamfer", "chamfer_or_penalty", "directed_chamfer", "aggregate", "evaluate_sample", "format_table",
           "iou", "resim_cd", "resim_scans", "street_cd", "tmd"]

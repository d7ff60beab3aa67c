"""A PNG that shows at a glance what a sample holds: ground truth by class, the input over it, and 3D."""
from __future__ import annotations

import json
import os

import numpy as np

from hgca_core.synth.assets import LABEL_NAMES

LABEL_COLORS = np.array([[0.62, 0.62, 0.62], [0.80, 0.72, 0.55], [0.85, 0.35, 0.25], [0.15, 0.45, 0.85],
                         [0.20, 0.65, 0.25], [0.55, 0.25, 0.70], [0.90, 0.65, 0.10], [0.10, 0.75, 0.75],
                         [0.95, 0.30, 0.65]])


def _subsample(n: int, k: int, seed: int = 0) -> np.ndarray:
    return np.arange(n) if n <= k else np.sort(np.random.default_rng(seed).choice(n, k, replace=False))


def render_preview(sample: dict, path: str | os.PathLike, max_points: int = 40_000) -> str:
    """Write a PNG: top view of the ground truth by class; top view of the input scans over the ground
    truth with poses and the street corridor; below, a 3D view of the input over the ground truth."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch, Rectangle

    gt, lab = np.asarray(sample["gt_surface"]), np.asarray(sample["gt_surface_label"])
    inp, sid = np.asarray(sample["input_points"]), np.asarray(sample["input_scan_index"])
    size = np.asarray(sample["region"])[3:6]
    ground = float(sample["ground_z"])
    meta = json.loads(str(sample["meta"]))
    poses, evals = np.asarray(sample["input_poses"]), np.asarray(sample["eval_poses"])

    fig = plt.figure(figsize=(15, 14), dpi=90)
    grid = fig.add_gridspec(2, 2, height_ratios=(1.0, 0.75))
    # (1) ground truth by class, drawn low to high so roofs and canopies cover the ground
    ax = fig.add_subplot(grid[0, 0])
    g = _subsample(len(gt), 3 * max_points)
    order = g[np.argsort(gt[g, 2])]
    ax.scatter(gt[order, 0], gt[order, 1], s=0.4, c=LABEL_COLORS[np.minimum(lab[order], len(LABEL_COLORS) - 1)],
               linewidths=0)
    ax.legend(handles=[Patch(color=LABEL_COLORS[i], label=n) for i, n in enumerate(LABEL_NAMES)],
              loc="upper right", fontsize=7, ncol=2, framealpha=0.8)
    ax.set_title(f"ground truth by class (seed {meta.get('seed')}, {meta.get('style')})")
    # (2) input over ground truth, poses, street corridor
    ax2 = fig.add_subplot(grid[0, 1])
    ax2.scatter(gt[g, 0], gt[g, 1], s=0.3, c="0.8", linewidths=0)
    k = _subsample(len(inp), 2 * max_points, 1)
    ax2.scatter(inp[k, 0], inp[k, 1], s=0.4, c=sid[k], cmap="turbo", vmin=0, vmax=max(1, len(poses) - 1), linewidths=0)
    for i, p in enumerate(poses):
        _arrow(ax2, p, "k" if i == 0 else "tab:blue")
    for p in evals:
        ax2.plot(p[0, 3], p[1, 3], marker="*", ms=14, color="tab:red", mec="k")
        _arrow(ax2, p, "tab:red")
    sb = np.asarray(sample["street_box"])
    ax2.add_patch(Rectangle(sb[:2], sb[2] - sb[0], sb[3] - sb[1], fill=False, ls="--", ec="tab:orange", lw=1.5))
    ax2.set_title(f"input: {len(poses)} scans, {len(inp):,} points (ego black, eval red)")
    for a in (ax, ax2):
        a.add_patch(Rectangle((0, 0), size[0], size[1], fill=False, ec="k", lw=1.2))
        a.set_xlim(-1, size[0] + 1)
        a.set_ylim(-1, size[1] + 1)
        a.set_aspect("equal")
        a.set_xlabel("x (m, region frame)")
        a.set_ylabel("y (m)")
    # (3) 3D: a perspective view from above one sidewalk, ground truth by class (pale), input on top
    ax3 = fig.add_subplot(grid[1, :])
    g3 = _subsample(len(gt), 3 * max_points, 2)
    k3 = _subsample(len(inp), 2 * max_points, 3)
    eye = np.array([-12.0, size[1] * 0.5 - 4.0, ground + 15.0])                # above the street, behind it
    target = np.array([size[0] * 0.6, size[1] * 0.5, ground + 1.0])
    pale = 0.55 * LABEL_COLORS[np.minimum(lab[g3], len(LABEL_COLORS) - 1)] + 0.45
    pts = np.concatenate([gt[g3], inp[k3]])
    cols = np.concatenate([pale, plt.get_cmap("plasma")(np.clip((inp[k3, 2] - ground) / 4.0, 0, 1))[:, :3] * 0.85])
    uv, depth = _project(pts, eye, target)
    order = np.argsort(-depth)                              # far first, near points on top
    ax3.scatter(uv[order, 0], uv[order, 1], s=np.where(order < len(g3), 0.6, 0.9), c=cols[order], linewidths=0)
    ax3.set_aspect("equal")
    ax3.axis("off")
    ax3.set_title("3D view along the street: input (coloured by height) over ground truth (pale, by class)")
    fig.tight_layout()
    path = os.fspath(path)
    tmp = f"{path}.tmp.png"
    fig.savefig(tmp)
    plt.close(fig)
    os.replace(tmp, path)
    return path


def _project(points: np.ndarray, eye: np.ndarray, target: np.ndarray, focal: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection (x right, y up on the image) of points seen from `eye` looking at `target`."""
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    rel = np.asarray(points, dtype=np.float64) - eye
    depth = rel @ fwd
    depth = np.maximum(depth, 1e-3)
    return np.c_[rel @ right, rel @ up] * (focal / depth)[:, None], depth


def _arrow(ax, pose: np.ndarray, color: str) -> None:
    x, y = pose[0, 3], pose[1, 3]
    ax.plot(x, y, "o", ms=5, color=color, mec="k", mew=0.5)
    ax.arrow(x, y, 2.0 * pose[0, 0], 2.0 * pose[1, 0], width=0.12, color=color, length_includes_head=True)

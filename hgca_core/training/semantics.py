"""Training the semantic head (`hgca train --recipe semantics`) on the synthetic streets' surface labels.

Targets: each ground-truth 20 cm cell (`gt_occ20`) takes the majority label of the ground-truth surface samples
inside it (`gt_surface_label`), or the nearest sample's where none falls inside. Inputs: those cells with the
observed flag of the sample's own input, perturbed so that they look like a completed state rather than the
ground truth: cells dropped and added next to others (a sampled state's fuzz), turns (90 degree steps and flips,
or any yaw resampled to the grid), and cuts of the observed flag above a height and beyond a half-plane (what a
sensor misses and the chain generates). The model and its features are `hgca_core.models.semantics`.

The head's input follows `SemanticsConfig.placement`. "coarse-features": the frozen shipped coarse kernel runs on
each perturbed example (its observed cells as x^0). "fine-latents": the frozen shipped fine stage's autoencoder
encodes each scene's ground-truth 10 cm cells once (all its distance pairs and surface points, as the fine
stage's own targets), pooled per 20 cm cell; the pooled codes travel with their cells through the perturbation
(a turn moves cells, not the codes' frame) and an added cell has none, as a coarse cell the fine stage leaves empty.

The task plugs into the shared trainer (`hgca_core.training.trainer`) as a chain of one step: every example is
used once. Validation scores fixed, perturbed full val scenes (the same cells for every placement); `val_iou` is
their mIoU over the classes present.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import nn

from hgca_core.geometry.keys import pack
from hgca_core.geometry.nearest import PointIndex
from hgca_core.geometry.voxel import COARSE, cell_centers, point_cells, voxelize
from hgca_core.models.semantics import (CLASS_NAMES, SemanticHead, SemanticsConfig, coarse_features, fine_features,
                                        fitted_ground, head_input)
from hgca_core.training.buffer import Chain
from hgca_core.dataset.samples import load_arrays, split_files

DROP = (0.0, 0.2)        # share of cells dropped per example (drawn uniformly)
ADD = (0.0, 0.1)         # share of cells added next to others
CUT_HEIGHT = (1.5, 3.0)  # metres above the fitted ground: the observed flag is cleared above a drawn height
LABEL_SMOOTHING = 0.05
REFRESH = 50             # examples between looks for new train scenes (a split still being built)


def cell_labels(cells: np.ndarray, surface: np.ndarray, surface_label: np.ndarray) -> np.ndarray:
    """(M,) uint8 label of each 20 cm cell: the majority of the surface samples inside (the cell a point falls in
    as `voxelize` puts it), else the nearest's."""
    c = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    pc = point_cells(surface, COARSE)
    lab = np.asarray(surface_label, dtype=np.int64)
    k = pack(pc) * 16 + lab
    uk, counts = np.unique(k, return_counts=True)
    cell_k, cell_lab = uk // 16, uk % 16
    order = np.lexsort((-counts, cell_k))           # per cell, the most frequent label first
    cell_k, cell_lab = cell_k[order], cell_lab[order]
    first = np.r_[True, cell_k[1:] != cell_k[:-1]]
    cell_k, cell_lab = cell_k[first], cell_lab[first]
    ck = pack(c)
    pos = np.clip(np.searchsorted(cell_k, ck), 0, max(len(cell_k) - 1, 0))
    hit = (cell_k[pos] == ck) if len(cell_k) else np.zeros(len(c), bool)
    out = np.zeros(len(c), np.uint8)
    out[hit] = cell_lab[pos[hit]]
    if (~hit).any() and len(surface):
        i = PointIndex(surface).nearest(cell_centers(c[~hit], COARSE))[1]
        out[~hit] = lab[i]
    return out


def scene(path: str | Path) -> dict[str, np.ndarray]:
    """A sample's ground-truth cells (M, 3), their labels (M,) and observed flags (M,), and its 20 cm grid."""
    a = load_arrays(str(path), ("region", "input_points", "gt_occ20", "gt_surface", "gt_surface_label"))
    cells = a["gt_occ20"].astype(np.int64)
    size = a["region"][3:6]
    s0 = voxelize(a["input_points"], COARSE, size)
    observed = np.isin(pack(cells), pack(s0))
    return {"cells": cells, "labels": cell_labels(cells, a["gt_surface"], a["gt_surface_label"]),
            "observed": observed, "grid": np.array([int(round(v / COARSE)) for v in size])}


def perturb(cells: np.ndarray, labels: np.ndarray, observed: np.ndarray, rng: np.random.Generator,
            crop: int | None = None, source: bool = False) -> tuple[np.ndarray, ...]:
    """(cells, labels, observed) of one training example: a crop of `crop` x `crop` cells (None: all), turned,
    with cells dropped and added and the observed flag cut (see the module docstring). With `source`, also (N,)
    the index of each cell's cell in `cells` (-1 for an added one), which carries per-cell features along; the
    random draws are the same either way."""
    c, lab, obs = np.asarray(cells, np.int64), np.asarray(labels), np.asarray(observed, bool)
    origin = np.arange(len(c))
    if crop is not None and len(c):
        lo, hi = c[:, :2].min(0), c[:, :2].max(0)
        start = np.array([rng.integers(lo[i], max(lo[i] + 1, hi[i] - crop + 2)) for i in range(2)])
        keep = np.all((c[:, :2] >= start) & (c[:, :2] < start + crop), 1)
        c, lab, obs, origin = c[keep] - np.r_[start, 0], lab[keep], obs[keep], origin[keep]
    if len(c) == 0:
        return (c, lab, obs, origin) if source else (c, lab, obs)
    centre = (c[:, :2].max(0) + c[:, :2].min(0)) / 2.0
    xy = c[:, :2] + 0.5 - centre
    if rng.random() < 0.5:                                      # any yaw, resampled to the grid
        a = rng.uniform(0, 2 * np.pi)
        rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        xy = xy @ rot.T
    else:                                                       # 90 degree steps and a flip: exact
        for _ in range(int(rng.integers(4))):
            xy = np.c_[-xy[:, 1], xy[:, 0]]
        if rng.random() < 0.5:
            xy[:, 0] = -xy[:, 0]
    c = np.c_[np.floor(xy - xy.min(0)).astype(np.int64), c[:, 2]]
    _, first = np.unique(pack(c), return_index=True)
    c, lab, obs, origin = c[first], lab[first], obs[first], origin[first]
    drop = rng.random(len(c)) < rng.uniform(*DROP) * np.where(obs, 0.3, 1.0)   # generated cells are the fuzzy ones
    if drop.all():
        drop[:] = False
    c, lab, obs, origin = c[~drop], lab[~drop], obs[~drop], origin[~drop]
    n_add = int(len(c) * rng.uniform(*ADD))
    if n_add:
        src = rng.integers(len(c), size=n_add)
        step = rng.integers(-1, 2, size=(n_add, 3))
        new = c[src] + step
        new = new[new[:, 2] >= 0]
        fresh = ~np.isin(pack(new), pack(c))
        new = new[fresh]
        _, first = np.unique(pack(new), return_index=True)
        new = new[first]
        if len(new):
            i = PointIndex(c).nearest(new)[1]
            c, lab, obs = np.r_[c, new], np.r_[lab, lab[i]], np.r_[obs, np.zeros(len(new), bool)]
            origin = np.r_[origin, np.full(len(new), -1)]
            c = np.c_[c[:, :2] - c[:, :2].min(0), c[:, 2]]
    obs = obs.copy()
    if rng.random() < 0.5:
        hag = cell_centers(c, COARSE)[:, 2] - fitted_ground(c)
        obs &= hag < rng.uniform(*CUT_HEIGHT)
    if rng.random() < 0.5:
        a = rng.uniform(0, 2 * np.pi)
        d = (c[:, :2] - c[:, :2].mean(0)) @ np.array([np.cos(a), np.sin(a)])
        obs &= d < rng.uniform(-0.2, 0.5) * np.ptp(d)
    return (c, lab, obs, origin) if source else (c, lab, obs)


def batch_coords(sets: Sequence[np.ndarray]) -> tuple[torch.Tensor, np.ndarray]:
    """(N, 4) batched coords in key order for several cell sets, and the permutation from their concatenation."""
    from hgca_core.geometry.coords import pack

    coords = torch.cat([torch.cat([torch.full((len(s), 1), b, dtype=torch.long), torch.from_numpy(s)], 1)
                        for b, s in enumerate(sets)])
    order = torch.argsort(pack(coords))
    return coords[order], order.numpy()


class SemanticsLoss(nn.Module):
    """Weighted cross-entropy of the head on a batch of examples (chains of one step)."""

    def __init__(self, cfg: SemanticsConfig, class_weight: torch.Tensor | None = None) -> None:
        super().__init__()
        self.cfg = cfg
        self.model = SemanticHead(cfg)
        self.register_buffer("class_weight", class_weight if class_weight is not None else torch.ones(cfg.classes))

    def forward(self, chains: list[Chain]) -> tuple[torch.Tensor, dict, list[torch.Tensor]]:
        sets = [ch.state.cpu().numpy() for ch in chains]
        coords, order = batch_coords(sets)
        feats = torch.cat([ch.extra["feats"] for ch in chains])[order]
        target = torch.cat([ch.extra["labels"] for ch in chains])[order].long()
        dev = self.class_weight.device
        logits = self.model(coords.to(dev), feats.to(dev))
        loss = nn.functional.cross_entropy(logits.float(), target.to(dev), weight=self.class_weight,
                                           label_smoothing=LABEL_SMOOTHING)
        acc = float((logits.argmax(1) == target.to(dev)).float().mean())
        return loss, {"acc": acc}, [torch.zeros((0, 3), dtype=torch.long) for _ in chains]


def confusion(pred: np.ndarray, gt: np.ndarray, classes: int = len(CLASS_NAMES)) -> np.ndarray:
    """(classes, classes) counts, rows ground truth, columns prediction."""
    return np.bincount(np.asarray(gt, np.int64) * classes + np.asarray(pred, np.int64),
                       minlength=classes * classes).reshape(classes, classes)


def class_iou(conf: np.ndarray) -> np.ndarray:
    """Per-class IoU from a confusion matrix; NaN for classes absent from both prediction and ground truth."""
    tp = np.diag(conf).astype(np.float64)
    union = conf.sum(0) + conf.sum(1) - tp
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(conf.sum(1) > 0, tp / np.maximum(union, 1), np.nan)


@dataclass
class SemanticsTask:
    """The semantic head for the shared trainer."""

    data_dir: str | Sequence[str]
    cfg: SemanticsConfig = field(default_factory=SemanticsConfig)
    crop: int = 96
    val_count: int = 6
    name: str = "semantics"

    def __post_init__(self) -> None:
        self.train_files = split_files(self.data_dir, "train")
        self._scenes: dict[str, dict] = {}
        self._drawn = 0
        self.cfg.in_channels()                 # an unknown placement fails before any data is read
        self._frozen: torch.nn.Module | None = None

    def frozen(self) -> torch.nn.Module | None:
        """The frozen stage the placement reads (the shipped coarse kernel or the fine stage's autoencoder)."""
        if self._frozen is None and self.cfg.placement != "geometry":
            from hgca_core.models.weights import load_coarse, load_fine

            self._frozen = load_coarse()[0] if self.cfg.placement == "coarse-features" else load_fine()[1]
            self._frozen.requires_grad_(False)
        return self._frozen

    def _scene(self, path: Path) -> dict:
        key = str(path)
        if key not in self._scenes:
            s = scene(path)
            if self.cfg.placement == "fine-latents":
                s["pooled"] = cached_latents(self.frozen(), path, s["cells"])
            self._scenes[key] = s
        return self._scenes[key]

    def features(self, s: dict, c: np.ndarray, obs: np.ndarray, src: np.ndarray) -> np.ndarray:
        """The head's input for perturbed cells `c` of scene `s` (`src`: their source cells, -1 for added ones)."""
        extra = None
        if self.cfg.placement == "coarse-features":
            z = max(int(s["grid"][2]), int(c[:, 2].max()) + 1 if len(c) else 1)
            grid = (*(int(v) for v in np.maximum(c[:, :2].max(0) + 1, 1)), z) if len(c) else (1, 1, z)
            extra = coarse_features(self.frozen(), c, c[obs], grid)
        elif self.cfg.placement == "fine-latents":
            extra = np.zeros((len(c), s["pooled"].shape[1]), np.float32)
            extra[src >= 0] = s["pooled"][src[src >= 0]]
        return head_input(self.cfg, c, obs, extra)

    def class_weight(self, n: int = 8) -> torch.Tensor:
        """1 / sqrt(frequency) of the classes over the first `n` train scenes, mean 1 over the classes seen."""
        counts = np.zeros(self.cfg.classes)
        for p in self.train_files[:n]:
            counts += np.bincount(self._scene(p)["labels"], minlength=self.cfg.classes)[: self.cfg.classes]
        w = np.where(counts > 0, 1.0 / np.sqrt(np.maximum(counts, 1) / max(counts.sum(), 1)), 0.0)
        w = np.minimum(w / w[counts > 0].mean(), 5.0)
        return torch.tensor(w, dtype=torch.float32)

    def build(self) -> SemanticsLoss:
        return SemanticsLoss(self.cfg, self.class_weight())

    def recipe(self) -> dict:
        return {"crop": self.crop, "drop": DROP, "add": ADD, "cut_height": CUT_HEIGHT, "placement": self.cfg.placement}

    def new_example(self, rng: np.random.Generator) -> Chain:
        self._drawn += 1
        if self._drawn % REFRESH == 0:       # scenes still being built join the run as they are written
            self.train_files = split_files(self.data_dir, "train")
        path = self.train_files[int(rng.integers(len(self.train_files)))]
        s = self._scene(path)
        c, lab, obs, src = perturb(s["cells"], s["labels"], s["observed"], rng, self.crop, source=True)
        feats = torch.from_numpy(self.features(s, c, obs, src))
        t = torch.from_numpy(c)
        grid = tuple(int(v) for v in np.maximum(c.max(0) + 1, 1)) if len(c) else (1, 1, 1)
        return Chain(s0=t, gt=t, state=t, t=0, grid=grid,
                     extra={"feats": feats, "labels": torch.from_numpy(lab.astype(np.int64))})

    @torch.no_grad()
    def validate(self, loss_module: SemanticsLoss, seed: int = 0) -> dict:
        """mIoU (`val_iou`) and accuracy over fixed, perturbed full val scenes."""
        from hgca_core.models.semantics import predict

        conf = np.zeros((self.cfg.classes, self.cfg.classes), np.int64)
        for k, path in enumerate(split_files(self.data_dir, "val")[: self.val_count]):
            s = self._scene(path)
            c, lab, obs, src = perturb(s["cells"], s["labels"], s["observed"], np.random.default_rng(1000 + k),
                                       source=True)
            extra = None if self.cfg.placement == "geometry" else self.features(s, c, obs, src)[:, 1:]
            conf += confusion(predict(loss_module.model, c, obs, extra)[0], lab, self.cfg.classes)
        loss_module.train()
        iou = class_iou(conf)
        return {"val_iou": float(np.nanmean(iou)), "val_acc": float(np.trace(conf) / max(conf.sum(), 1)),
                **{f"val_iou_{n}": float(v) for n, v in zip(CLASS_NAMES, iou) if np.isfinite(v)}}


@torch.no_grad()
def scene_latents(autoencoder: nn.Module, path: str | Path, cells: np.ndarray) -> np.ndarray:
    """(M, K + 1) `fine_features` of a sample's ground-truth 20 cm `cells`: the frozen autoencoder's latents of
    its ground-truth 10 cm cells from all their distance pairs and surface points (the fine stage's targets)."""
    from hgca_core.training.fine import gt_latents

    a = load_arrays(str(path), ("gt_occ10", "udf_points", "udf_dist", "gt_surface"))
    c10 = torch.from_numpy(a["gt_occ10"].astype(np.int64))
    z = gt_latents(autoencoder, c10, torch.from_numpy(a["udf_points"]), torch.from_numpy(a["udf_dist"]),
                   torch.from_numpy(a["gt_surface"]))
    return fine_features(cells, c10.numpy(), z.cpu().numpy())


def latents_path(path: str | Path) -> Path:
    """The pooled-latent sidecar of a sample, named for the fine weights that encoded it:
    sample_X.npz -> sample_X.latents20-<sha256 of fine.pt, 12 digits>.npy."""
    from hgca_core.io.digest import file_digest
    from hgca_core.models.weights import shipped

    p = Path(path)
    return p.with_name(f"{p.name.removesuffix('.npz')}.latents20-{file_digest(shipped('fine'))[:12]}.npy")


def cached_latents(autoencoder: nn.Module, path: str | Path, cells: np.ndarray) -> np.ndarray:
    """`scene_latents` as float16, kept in a sidecar beside the sample (8-10 s of CPU a scene to encode, read back
    in milliseconds; a run resumed in sessions would pay it again per session). A sidecar older than its sample,
    of the wrong shape or unreadable is recomputed; a folder that cannot be written to only costs the time."""
    from hgca_core.errors import InputError
    from hgca_core.io.atomic import atomic_write

    side = latents_path(path)
    try:
        if side.stat().st_mtime_ns >= Path(path).stat().st_mtime_ns:
            z = np.load(side, allow_pickle=False)
            if z.dtype == np.float16 and z.shape[0] == len(cells):
                return z
    except (OSError, ValueError):
        pass
    z = scene_latents(autoencoder, path, cells).astype(np.float16)
    try:
        atomic_write(side, lambda f: np.save(f, z))
    except InputError:
        pass
    return z


def export_semantics(ckpt_path: str | Path, dest: str | Path, meta: dict | None = None) -> Path:
    """Write the head of a training run as weights of kind 'semantics': the weight average kept at the run's best
    validation mIoU (`best.pt` beside the checkpoint, the recipe's selection on val), else the checkpoint's own
    average. Why: the val mIoU of perturbed scenes swings by a few points between checks, and the last check is
    not always the best one. The record names the step and score it was selected at."""
    from hgca_core.models.weights import trained_weights
    from hgca_core.training.export import save_weights
    from hgca_core.training.selection import selected_run   # every stage's exporter picks its weights there

    ck, record, _ = selected_run(ckpt_path)
    module = SemanticsLoss(SemanticsConfig.from_dict(ck["config"]))
    module.load_state_dict(trained_weights(ck))
    return save_weights(dest, module.model, {**record, **(meta or {})})

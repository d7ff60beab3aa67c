"""The semantic head: a class for every cell of a completed 20 cm state, and so for every face of its mesh.

Why a separate network: the geometry must not change. The head reads the final coarse state (observed and
generated cells alike) and nothing the chain samples from, so adding it changes no cell, no vertex and no random
draw of a completion. It is a small sparse U-Net (`hgca_core.nn.unet`) on the occupied cells only, with
geometry-only features per cell: whether the input observed it, its height above the ground fitted to the state
itself, the height of its column's top above that ground, and a sinusoidal encoding of the height. LiDAR
intensity is left out: sensors scale it differently and the generated cells have none.

Where the head sits (`SemanticsConfig.placement`; the same U-Net in every case, only its input differs):
- "geometry" (the shipped head): the geometry-only features above (`cell_features`);
- "coarse-features": the frozen coarse kernel run once on the final 20 cm state with the input's cells as its
  x^0, its last decoder features (before the occupancy logit) at each cell (`coarse_features`);
- "fine-latents": per 20 cm cell the mean latent of its occupied 10 cm children and their share of the eight
  (`fine_features`): the fine chain's latents at inference, the autoencoder's encoding of the ground truth in
  training.
Every placement also sees the observed flag. The frozen stages are only read, so geometry is the same with any.

Classes are `hgca_core.io.classes.CLASS_NAMES`, the synthetic streets' `LABEL_NAMES` in their order. Faces take the
class of the cell nearest to their centroid.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from scipy import ndimage
from torch import nn

from hgca_core.geometry.keys import pack
from hgca_core.geometry.nearest import PointIndex
from hgca_core.geometry.voxel import COARSE, cell_centers
from hgca_core.io.classes import CLASS_COLORS, CLASS_NAMES  # noqa: F401  (re-exported)
from hgca_core.models.config import Config
from hgca_core.nn.encoding import sinusoidal
from hgca_core.nn.sparse import SparseTensor
from hgca_core.nn.unet import SparseUNet

GROUND_TILE = 10      # cells (2 m) per ground tile: the lowest cell per tile is a ground sample
GROUND_WINDOW = 3     # tiles: the ground at a tile is the lowest sample within this window (a car roof is no ground)
HEIGHT_SCALE = 4.0    # metres: heights enter the network divided by this
PLACEMENTS = ("geometry", "coarse-features", "fine-latents")
COARSE_WIDTH = 16     # the shipped coarse U-Net's finest decoder width (GCAConfig.channels[0])
LATENT = 32           # the shipped autoencoder's latent size (AutoencoderConfig.latent)


@dataclass
class SemanticsConfig(Config):
    channels: tuple[int, ...] = (16, 24, 32, 48)
    blocks: int = 1
    classes: int = len(CLASS_NAMES)
    pe_freq: int = 3
    steps: int = 1        # the shared trainer's chain length: each training example is used once
    placement: str = "geometry"   # the head's input (PLACEMENTS); files written before the field: geometry

    def in_channels(self) -> int:
        """Input features per cell of the placement (the observed flag included)."""
        if self.placement not in PLACEMENTS:
            raise ValueError(f"placement must be one of {', '.join(PLACEMENTS)}, not {self.placement!r}")
        return {"geometry": 3 + 2 * self.pe_freq, "coarse-features": 1 + COARSE_WIDTH,
                "fine-latents": 2 + LATENT}[self.placement]


def fitted_ground(cells: np.ndarray) -> np.ndarray:
    """(N,) ground height (metres, region frame) under each cell, fitted to the cells themselves: per 2 m tile the
    lowest cell, then the lowest of the tiles around it (GROUND_WINDOW), empty tiles filled from the nearest tile
    that has one. Works on any state (ground truth, a completion, a real scan's cells)."""
    c = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    if len(c) == 0:
        return np.zeros(0)
    tile = c[:, :2] // GROUND_TILE
    lo = tile.min(0)
    t = tile - lo
    shape = tuple(int(v) for v in t.max(0) + 1)
    low = np.full(shape, np.iinfo(np.int64).max, dtype=np.int64)
    np.minimum.at(low, (t[:, 0], t[:, 1]), c[:, 2])
    empty = low == np.iinfo(np.int64).max
    if empty.any():
        idx = ndimage.distance_transform_edt(empty, return_distances=False, return_indices=True)
        low = low[idx[0], idx[1]]
    low = ndimage.minimum_filter(low, size=GROUND_WINDOW, mode="nearest")
    return cell_centers(low[t[:, 0], t[:, 1]], COARSE)


def cell_features(cells: np.ndarray, observed: np.ndarray, pe_freq: int = 3) -> np.ndarray:
    """(N, 3 + 2 pe_freq) float32 features of the cells (N, 3) of a 20 cm state: observed flag, height above the
    fitted ground, height of the cell's column top above it (both / HEIGHT_SCALE) and the height's encoding."""
    c = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    z = cell_centers(c, COARSE)[:, 2]
    hag = z - fitted_ground(c)
    top = np.zeros(len(c))
    if len(c):
        _, inv = np.unique(c[:, :2], axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        col = np.full(inv.max() + 1, -np.inf)
        np.maximum.at(col, inv, hag)
        top = col[inv]
    base = np.stack([np.asarray(observed, dtype=np.float64).reshape(-1), hag / HEIGHT_SCALE,
                     top / HEIGHT_SCALE], 1).astype(np.float32)
    pe = sinusoidal(torch.from_numpy(np.clip(hag / (2 * HEIGHT_SCALE), -1.0, 1.0)[:, None]).float(), pe_freq)
    return np.concatenate([base, pe.numpy()], 1).astype(np.float32)


class SemanticHead(nn.Module):
    """Sparse U-Net: cell features -> one logit per class per cell (the cells are the input's, unchanged)."""

    def __init__(self, cfg: SemanticsConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.unet = SparseUNet(cfg.in_channels(), cfg.classes, channels=cfg.channels, blocks=cfg.blocks)

    def forward(self, coords: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """coords (N, 4) [b, x, y, z] unique and sorted (`coords.pack` order), feats (N, C) -> (N, classes)."""
        return self.unet(SparseTensor(coords, feats)).feats


def _sorted_batch(cells: np.ndarray) -> tuple[torch.Tensor, np.ndarray]:
    """(N, 4) batch-0 coords in the sparse tensors' key order, and the permutation that sorts `cells` so."""
    from hgca_core.geometry.coords import pack

    c = torch.from_numpy(np.asarray(cells, dtype=np.int64).reshape(-1, 3))
    coords = torch.cat([torch.zeros(len(c), 1, dtype=torch.long), c], 1)
    order = torch.argsort(pack(coords))
    return coords[order], order.numpy()


@torch.no_grad()
def coarse_features(kernel: nn.Module, cells: np.ndarray, s0: np.ndarray, grid: tuple[int, int, int]) -> np.ndarray:
    """(N, COARSE_WIDTH) float32: the frozen coarse kernel (`models.gca.GCAKernel`, eval mode) run once on the
    state `cells` (N, 3) with x^0 = `s0` (its input cells) in a `grid` (x, y, z cells), read at its U-Net's last
    decoder layer (the input of the occupancy logit) at each cell. Free space is left unknown in training and
    inference alike (a turned crop has no free grid). Read-only: a forward hook copies the layer's input and
    returns nothing, so the kernel's weights, outputs and random draws are untouched."""
    from hgca_core.geometry import coords as cs

    c = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    if len(c) == 0:
        return np.zeros((0, kernel.unet.channels[0]), np.float32)
    kernel.eval()
    dev = next(kernel.parameters()).device
    state = cs.with_batch(torch.from_numpy(c)).to(dev)
    x0 = cs.with_batch(torch.from_numpy(np.asarray(s0, dtype=np.int64).reshape(-1, 3))).to(dev)
    from hgca_core.nn.sparse import CellState

    grid = tuple(int(v) for v in grid)
    seen: list[torch.Tensor] = []
    hook = kernel.unet.head.register_forward_hook(lambda _m, inp, _out: seen.append(inp[0].feats.detach().clone()))
    try:
        nbhd = kernel.neighbourhood(CellState(state, grid))
        kernel(nbhd, state, x0, kernel.bev(CellState(x0, grid), 1, None), None)
    finally:
        hook.remove()
    rows = cs.lookup(state, cs.pack(nbhd.coords))        # nbhd is sorted by key and holds every state cell
    return seen[0][rows].float().cpu().numpy()


def fine_features(cells: np.ndarray, fine_cells: np.ndarray, latents: np.ndarray) -> np.ndarray:
    """(N, K + 1) float32 per 20 cm cell (N, 3): the mean latent of its occupied 10 cm children among
    `fine_cells` (M, 3) with `latents` (M, K), and the children's share of the eight (zeros without any)."""
    c = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    f = np.asarray(fine_cells, dtype=np.int64).reshape(-1, 3)
    z = np.asarray(latents, dtype=np.float32).reshape(len(f), -1)
    k = z.shape[1] if z.ndim == 2 and z.shape[1] else LATENT
    out = np.zeros((len(c), k + 1), np.float32)
    if len(c) == 0 or len(f) == 0:
        return out
    ck = pack(c)
    order = np.argsort(ck)
    pk = pack(f // 2)
    pos = np.clip(np.searchsorted(ck[order], pk), 0, len(c) - 1)
    hit = ck[order][pos] == pk
    row = order[pos[hit]]
    np.add.at(out[:, :k], row, z[hit])
    count = np.bincount(row, minlength=len(c)).astype(np.float32)
    out[:, :k] /= np.maximum(count, 1)[:, None]
    out[:, k] = count / 8.0
    return out


def head_input(cfg: SemanticsConfig, cells: np.ndarray, observed: np.ndarray,
               extra: np.ndarray | None = None) -> np.ndarray:
    """The head's (N, cfg.in_channels()) input: `cell_features` for the geometry placement, else the observed
    flag beside `extra`, the placement's features of the cells (`coarse_features`, `fine_features`)."""
    if cfg.placement == "geometry":
        return cell_features(cells, observed, cfg.pe_freq)
    if extra is None:
        raise ValueError(f"the {cfg.placement} head needs its features (coarse_features / fine_features)")
    obs = np.asarray(observed, dtype=np.float32).reshape(-1, 1)
    out = np.concatenate([obs, np.asarray(extra, dtype=np.float32).reshape(len(obs), -1)], 1)
    if out.shape[1] != cfg.in_channels():
        raise ValueError(f"the {cfg.placement} head reads {cfg.in_channels()} features a cell, got {out.shape[1]}")
    return out


@torch.no_grad()
def predict(head: SemanticHead, cells: np.ndarray, observed: np.ndarray,
            extra: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(labels (N,) uint8, probabilities (N, classes) float32) of the cells (N, 3) of a 20 cm state; `observed`
    (N,) bool marks the cells the input holds; `extra`: the placement's features (see `head_input`).
    Deterministic: float32, no sampling, one pass."""
    c = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    if len(c) == 0:
        return np.zeros(0, np.uint8), np.zeros((0, head.cfg.classes), np.float32)
    head.eval()
    dev = next(head.parameters()).device
    coords, order = _sorted_batch(c)
    feats = torch.from_numpy(head_input(head.cfg, c, observed, extra)[order])
    logits = head(coords.to(dev), feats.to(dev)).float().cpu()
    prob = torch.softmax(logits, 1).numpy()
    out = np.empty_like(prob)
    out[order] = prob
    return out.argmax(1).astype(np.uint8), out.astype(np.float32)


def observed_mask(cells: np.ndarray, input_cells: np.ndarray) -> np.ndarray:
    """(N,) bool: which of `cells` the input's cells hold."""
    c = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    s = np.asarray(input_cells, dtype=np.int64).reshape(-1, 3)
    if len(c) == 0 or len(s) == 0:
        return np.zeros(len(c), bool)
    return np.isin(pack(c), pack(s))


def face_labels(points: np.ndarray, cells: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(F,) uint8: the class of the cell (20 cm, region frame) nearest to each point (face centroids, region
    frame, metres)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0 or len(cells) == 0:
        return np.zeros(len(p), np.uint8)
    centres = cell_centers(cells, COARSE)         # the 20 cm cells' centres as every other stage places them
    i = PointIndex(centres).nearest(p)[1]
    return np.asarray(labels, dtype=np.uint8)[i]


def agreement(points: np.ndarray, own: np.ndarray, others: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """(F,) float32 share of the k samples whose labelled cells give each point (face centroid, region frame) the
    class `own` gives it (its own sample counts: 1.0 means every sample agrees). `others`: (cells, labels) of
    every sample, its own included, or only the others; 1.0 everywhere for a single sample."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not others:
        return np.ones(len(p), np.float32)
    votes = np.zeros(len(p))
    for cells, labels in others:
        votes += face_labels(p, cells, labels) == own
    return (votes / len(others)).astype(np.float32)


def label_mesh(head: SemanticHead, face_centres: np.ndarray, cells: np.ndarray,
               input_cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cell labels (N,), face labels (F,)) of one completion: the head on its 20 cm state `cells` (observed where
    `input_cells` holds them), each face centre (region frame, metres) given its nearest cell's class."""
    labels, _ = predict(head, cells, observed_mask(cells, input_cells))
    return labels, face_labels(face_centres, cells, labels)


def label_completions(head: SemanticHead, completions: list, input_cells: np.ndarray,
                      to_local: Callable[[np.ndarray], np.ndarray]) -> None:
    """Give every completion's mesh (`pipeline.Completion`: `.mesh`, `.coarse_cells`) the face attributes
    `label` (uint8, CLASS_NAMES index) and `label_agreement` (float32: the share of the k samples that give the
    face's place the same class, 1.0 with one sample). `input_cells`: the input's 20 cm cells; `to_local` maps the
    meshes' vertices into the region frame of the cells."""
    done = []
    for c in completions:
        centres = to_local(np.asarray(c.mesh.triangles_center, dtype=np.float64)) if len(c.mesh.faces) else \
            np.zeros((0, 3))
        cell_labels, faces = label_mesh(head, centres, c.coarse_cells, input_cells)
        done.append((centres, faces, (np.asarray(c.coarse_cells), cell_labels)))
    states = [d[2] for d in done]
    for c, (centres, faces, _) in zip(completions, done):
        c.mesh.face_attributes["label"] = faces
        c.mesh.face_attributes["label_agreement"] = agreement(centres, faces, states)

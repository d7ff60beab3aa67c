"""Scores of a finished drive for `benchmarks/drive.py`: seams against the ground truth (overlap bands, 4 m slabs
along the drive and where the weak ones come from), each Ray worker's memory per tile, and the page's PNG."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from hgca_core.geometry.keys import pack
from hgca_core.geometry.region import Region
from hgca_core.geometry.voxel import COARSE, cell_centers, voxelize
from hgca_core.tiling.plan import footprint_contains, owned
from hgca_core.tiling.store import DriveStore

SCENE = 120.0                    # the layout square of a scene; the street repeats its two layouts every 240 m
SLAB = 4.0                       # metres along the drive per slab of the seam table
ENDS = 20.0                      # metres at either end of the drive left out of the slab comparison


def centre_cells(cells: np.ndarray, source: Region, target: Region) -> np.ndarray:
    """Cells of `source` by their centres into `target`'s grid (one cell each; for agreement between tiles)."""
    return voxelize(target.to_local(source.to_world(cell_centers(cells, COARSE))), COARSE, target.size)


def scored_cells(pred: np.ndarray, gt: np.ndarray, region: Region) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cells a tile's result or its ground truth holds: their world centres and which of them are predicted
    and true, what the seam table and the slab counts count."""
    both = np.unique(np.concatenate([pred, gt]), axis=0)
    keys = pack(both)
    return region.to_world(cell_centers(both, COARSE)), np.isin(keys, pack(pred)), np.isin(keys, pack(gt))


def seam_scores(out: Path, gts: list[np.ndarray], x0: float, x1: float) -> dict:
    """On the merged result (each place scored on the tile that owns it): IoU against ground truth in the overlap
    bands and inside tiles, IoU between neighbours' cells in their overlaps, and recall / IoU per `SLAB` m along x
    (the drive runs along x) between x0 and x1, the worst slab against the median `ENDS` m away from either end."""
    doc = json.loads((out / "drive.json").read_text())
    store = DriveStore(out)
    regions = [Region.from_tuple(t["region"]) for t in doc["tiles"]]
    cells = [store.load(t["key"], only=0)["samples"][0]["cells"].astype(np.int64) for t in doc["tiles"]]
    counts = {"band": [0, 0], "interior": [0, 0]}
    edges = np.arange(x0, x1 + SLAB, SLAB)
    slab = np.zeros((3, len(edges) - 1))                   # hits, ground truth, predicted
    for i, (pred, gt) in enumerate(zip(cells, gts)):
        w, in_p, in_g = scored_cells(pred, gt, regions[i])
        mine = owned(w[:, :2], i, regions)
        cover = sum(footprint_contains(r, w[:, :2]).astype(int) for r in regions)
        for row, m in enumerate((in_p & in_g, in_g, in_p)):
            slab[row] += np.histogram(w[m & mine, 0], edges)[0]
            if row < 2:
                counts["band"][row] += int((m & mine & (cover >= 2)).sum())
                counts["interior"][row] += int((m & mine & (cover == 1)).sum())
    agree = []
    for i in range(len(regions) - 1):
        a, b = cells[i], centre_cells(cells[i + 1], regions[i + 1], regions[i])
        ka = pack(a[footprint_contains(regions[i + 1], regions[i].to_world(cell_centers(a, COARSE))[:, :2])])
        kb = pack(b[footprint_contains(regions[i + 1], regions[i].to_world(cell_centers(b, COARSE))[:, :2])])
        agree.append(np.intersect1d(ka, kb).size / max(1, np.union1d(ka, kb).size))
    band, inner = (counts[k][0] / max(1, counts[k][1]) for k in ("band", "interior"))
    mid = (edges[:-1] + edges[1:]) / 2
    away = (mid > x0 + ENDS) & (mid < x1 - ENDS) & (slab[1] > 0)
    recall = slab[0] / np.maximum(slab[1], 1)
    iou = slab[0] / np.maximum(slab[1] + slab[2] - slab[0], 1)
    worst = {}
    for name, v in (("recall", recall), ("iou", iou)):
        j = int(np.flatnonzero(away)[np.argmin(v[away])])
        med = float(np.median(v[away]))
        worst[name] = {"worst": round(float(v[j]), 4), "at_x": round(float(mid[j]), 1), "median": round(med, 4),
                       "ratio": round(float(v[j]) / med, 3)}
    return {"iou_band": round(band, 4), "iou_interior": round(inner, 4), "ratio": round(band / inner, 3),
            "neighbour_agreement": round(float(np.mean(agree)), 4),
            "agreement_per_overlap": [round(a, 3) for a in agree], "slabs": worst,
            "slab_x": mid.round(1).tolist(), "slab_recall": recall.round(4).tolist(),
            "slab_iou": iou.round(4).tolist(), "slab_away": away.tolist()}


def worker_growth(work: Path) -> dict | None:
    """Each Ray worker's peak RSS after each of its tiles (in finishing order), short against long drive."""
    seqs = {}
    for name in ("short", "long"):
        path = work / f"{name}_w2" / "drive.json"
        if not path.is_file():
            return None
        tiles = sorted(json.loads(path.read_text())["tiles"], key=lambda t: t["finished"])
        seqs[name] = [[t["peak_rss"] / 2**30 for t in tiles if t["worker"] == w] for w in {t["worker"] for t in tiles}]
    n = min(len(s) for s in seqs["short"])
    long_seq = max(seqs["long"], key=len)
    k = np.arange(n, len(long_seq) + 1)
    slope = np.polyfit(k, long_seq[n - 1:], 1)[0] if len(k) > 1 else 0.0
    return {"n": n, "short_at_n": round(max(s[n - 1] for s in seqs["short"]), 2),
            "long_at_n": round(max(s[n - 1] for s in seqs["long"]), 2), "long_tiles": len(long_seq),
            "long_last": round(long_seq[-1], 2), "mib_per_tile": round(float(slope) * 1024, 1)}


def slab_sources(seams: dict, doc: dict) -> dict:
    """Whether weak slabs come from the seams or from the street: the median recall of slabs that hold an
    ownership seam against the others, and the correlation of each slab's recall with the slab one street
    repeat (`2 * SCENE` m: the two layouts taken in turn) further on."""
    x, rec = np.array(seams["slab_x"]), np.array(seams["slab_recall"])
    away = np.array(seams["slab_away"])
    centres = np.array([t["region"][0] for t in doc["tiles"]])
    cuts = (centres[:-1] + centres[1:]) / 2
    at_seam = np.array([np.any(np.abs(cuts - v) <= SLAB / 2) for v in x])
    shift = int(round(2 * SCENE / SLAB))
    both = away[:-shift] & away[shift:]
    corr = float(np.corrcoef(rec[:-shift][both], rec[shift:][both])[0, 1])
    return {"recall_median_seam_slabs": round(float(np.median(rec[away & at_seam])), 4),
            "recall_median_other_slabs": round(float(np.median(rec[away & ~at_seam])), 4),
            "seam_slabs": int((away & at_seam).sum()), "repeat_correlation": round(corr, 3)}


def plot(out: Path, path: Path, scores: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    doc = json.loads((out / "drive.json").read_text())
    regions = [Region.from_tuple(t["region"]) for t in doc["tiles"]]
    fig, ax = plt.subplots(2, 1, figsize=(16, 6.5), gridspec_kw={"height_ratios": [1, 1.2]}, sharex=True)
    cmap = plt.get_cmap("tab10")
    for i, r in enumerate(regions):
        corners = r.to_world(np.array([[0, 0, 0], [r.size[0], 0, 0], [r.size[0], r.size[1], 0], [0, r.size[1], 0],
                                       [0, 0, 0]], float))
        ax[0].plot(corners[:, 0], corners[:, 1] + (i % 2) * 0.6, color=cmap(i % 10), lw=0.8)
    pos = np.array([s["position"] for s in doc["scans"]])
    ax[0].plot(pos[:, 0], pos[:, 1], "k.", ms=2, label="scan positions")
    ax[0].set_title(f"tile footprints along the drive ({len(regions)} tiles; odd tiles drawn 0.6 m up to tell them "
                    "apart)")
    ax[0].legend(loc="upper right")
    x = np.array(scores["slab_x"])
    away = np.array(scores["slab_away"])
    for key, label in (("slab_recall", "recall of the ground truth"), ("slab_iou", "IoU")):
        v = np.array(scores[key])
        ax[1].plot(x[away], v[away], ".-", lw=0.8, ms=3, label=f"{label} per {SLAB:g} m slab")
    for r in regions[:-1]:
        ax[1].axvline(r.center[0] + (regions[1].center[0] - regions[0].center[0]) / 2, color="0.85", lw=0.6, zorder=0)
    w = scores["slabs"]["recall"]
    ax[1].axhline(w["median"], color="C0", ls=":", lw=0.8)
    ax[1].axhline(0.8 * w["median"], color="C3", ls="--", lw=0.8, label="0.8 x median recall")
    ax[1].set_ylim(0, 1)
    ax[1].set_xlabel("x along the drive (m); grey lines: ownership seams between tiles")
    ax[1].legend(loc="lower right", fontsize=8, ncol=3)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)

"""How high do the structures that cross a 2 m cut go, on real scans and on synthetic sweeps? (run by hand)
`python benchmarks/structure_tops.py --data data/synth2 --out benchmarks/results/structure_tops.json`

Why: most cells the coarse model grows above a 2 m cut into space the real rays saw empty stand over or beside a
structure the cut crossed (`violation_anatomy.py`): the model carries such structures upward past where they end.
It learned how far they go on from the synthetic streets. This compares that prior with the real logs: for every
20 cm column the input holds 1.6-2.0 m above the ground, the highest input cell within 20 cm of it (3 x 3 columns),
binned by height; the same on the first sweeps of synthetic val scenes (what the sensor saw, as on the real logs)
and on their ground truth (what the model is trained to grow). A real distribution that ends lower than the
synthetic one says the streets need more structures that stop at 2-4 m.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
BINS = (1.6, 2.0, 2.5, 3.5, 5.0, 7.0)   # top height bands (m above the ground); the last band is open


def tops(cells: np.ndarray, shape: tuple[int, int, int]) -> dict:
    """Columns crossing 1.6-2.0 m and the height bands of their highest cell within one column around."""
    from scipy.ndimage import maximum_filter

    from hgca_core.geometry.region import BELOW_GROUND, height_layer
    from hgca_core.geometry.voxel import COARSE, column_tops

    occ = np.zeros(shape, dtype=bool)
    occ[cells[:, 0], cells[:, 1], cells[:, 2]] = True
    layer = lambda h: height_layer(h, COARSE)  # noqa: E731
    crossing = occ[:, :, layer(1.6):layer(2.0)].any(axis=2)
    top = column_tops(occ)
    height = (maximum_filter(top, size=3)[crossing] + 1) * COARSE - BELOW_GROUND   # top face of the top cell
    edges = [*BINS[1:], np.inf]
    counts = [int(((height >= lo) & (height < hi)).sum()) for lo, hi in zip(BINS, edges)]
    n = max(int(crossing.sum()), 1)
    return {"columns": int(crossing.sum()), "median_top_m": round(float(np.median(height)), 2) if len(height) else None,
            "bands_pct": {f"{lo:g}-{hi:g}": round(100.0 * c / n, 1) for lo, hi, c in zip(BINS, edges, counts)},
            **thin(occ, crossing, layer)}


def thin(occ: np.ndarray, crossing: np.ndarray, layer) -> dict:
    """Thin things the cut crosses (a 2D piece of at most 4 columns at 1.6-2 m: poles, trunks, posts) and how many
    of them carry something 2.6-5 m up within 1.2 m around (a crown, a lamp head, a sign board)."""
    from scipy.ndimage import binary_dilation, label

    pieces, n = label(crossing, structure=np.ones((3, 3), bool))
    sizes = np.bincount(pieces.ravel(), minlength=n + 1)
    high = occ[:, :, layer(2.6):layer(5.0)].any(axis=2)
    ids = [i for i in range(1, n + 1) if sizes[i] <= 4]
    crowned = sum(bool(high[binary_dilation(pieces == i, iterations=6)].any()) for i in ids)
    return {"thin": len(ids), "thin_with_top_pct": round(100.0 * crowned / max(len(ids), 1), 1)}


def real_rows(real_dir: Path) -> dict:
    from hgca_core.commands.eval_real import default_items
    from hgca_core.geometry.region import Region
    from hgca_core.geometry.voxel import COARSE, voxelize
    from hgca_core.real_eval import input_rays

    rows = {}
    for item in default_items(real_dir):
        name = item["name"]
        points, origins, _ = input_rays(item)
        region = Region.around(points, sensor=origins[0])
        local = region.to_local(points)
        local = local[region.contains_local(local)]
        rows[name] = tops(voxelize(local, COARSE, region.size), region.grid_shape(COARSE))
    return rows


def synthetic_rows(data: Path, count: int) -> dict:
    from hgca_core.geometry.region import Region
    from hgca_core.geometry.voxel import COARSE, voxelize
    from hgca_core.synth.dataset import load_sample
    from hgca_core.training.data import split_files

    rows = {}
    for path in split_files(str(data), "val")[:count]:
        s = load_sample(path)
        first = np.asarray(s["input_scan_index"]) == 0
        points = np.asarray(s["input_points"], dtype=np.float64)[first]
        origin = np.asarray(s["input_origins"], dtype=np.float64)[0]
        region = Region.around(points, sensor=origin)
        shape = region.grid_shape(COARSE)
        local = region.to_local(points)
        sweep = tops(voxelize(local[region.contains_local(local)], COARSE, region.size), shape)
        gt = region.to_local(np.asarray(s["gt_surface"], dtype=np.float64))
        truth = tops(voxelize(gt[region.contains_local(gt)], COARSE, region.size), shape)
        rows[Path(path).stem] = {"profile": json.loads(str(s["meta"]))["profile"], "sweep": sweep, "truth": truth}
    return rows


def pooled(rows: list[dict]) -> dict:
    """Bands over all columns of several inputs (weighted by their columns), thin things over all of them."""
    n, t = sum(r["columns"] for r in rows), sum(r["thin"] for r in rows)
    keys = rows[0]["bands_pct"].keys()
    return {"columns": n, "bands_pct": {k: round(sum(r["bands_pct"][k] * r["columns"] for r in rows) / max(n, 1), 1)
                                        for k in keys},
            "thin": t, "thin_with_top_pct": round(sum(r["thin_with_top_pct"] * r["thin"] for r in rows) / max(t, 1), 1)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=str(REPO / "data" / "synth2"), help="dataset folder with a val split")
    p.add_argument("--count", type=int, default=16, help="val scenes")
    p.add_argument("--real-dir", default=str(REPO.parent / "shared" / "fixtures" / "real"))
    p.add_argument("--out", required=True, help="JSON file (the table goes beside it as .md)")
    args = p.parse_args(argv)
    real, synth = real_rows(Path(args.real_dir)), synthetic_rows(Path(args.data), args.count)
    bands = list(next(iter(real.values()))["bands_pct"])
    lines = ["| input | columns crossing 1.6-2 m | " + " | ".join(f"top {b} m (%)" for b in bands)
             + " | thin things crossing | with something 2.6-5 m up within 1.2 m (%) |",
             "|---|---:|" + "---:|" * (len(bands) + 2)]

    def row(label: str, r: dict) -> str:
        return (f"| {label} | {r['columns']:,} | " + " | ".join(f"{r['bands_pct'][b]:.1f}" for b in bands)
                + f" | {r['thin']} | {r['thin_with_top_pct']:.1f} |")

    lines += [row(f"real: {k}", v) for k, v in real.items()]
    sweeps = pooled([v["sweep"] for v in synth.values()])
    lines.append(row(f"synthetic val first sweeps ({len(synth)}, pooled)", sweeps))
    lines.append(row("their ground truth (pooled)", pooled([v["truth"] for v in synth.values()])))
    for prof in sorted({v["profile"] for v in synth.values()}):
        sel = [v for v in synth.values() if v["profile"] == prof]
        lines.append(row(f"synthetic first sweeps, {prof} ({len(sel)})", pooled([v["sweep"] for v in sel])))
    out = Path(args.out)
    out.write_text(json.dumps({"data": args.data, "real": real, "synthetic": synth}, indent=1) + "\n")
    text = ("Structures crossing a 2 m cut: for each 20 cm column the input holds 1.6-2.0 m above the ground, the "
            "highest cell within 20 cm of it (top face, metres above the ground), in bands; shares of the columns. "
            "Thin things: 2D pieces of at most 4 such columns (poles, trunks, posts), and the share of them with any "
            "input cell 2.6-5 m up within 1.2 m around (a crown, a lamp head, a sign).\n\n"
            + "\n".join(lines) + "\n")
    out.with_suffix(".md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

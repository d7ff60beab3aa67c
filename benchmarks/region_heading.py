"""Does a region turned to the vehicle's heading, as every training region is, complete real scans better? (by hand)
`python benchmarks/region_heading.py --out benchmarks/results/region_heading.json [--baseline B.json ...]`

Why: a synthetic sample's region has its x axis along the ego vehicle's heading (`synth.dataset`), so the model
has seen streets along x (flipped at random, never turned). `hgca complete` places the default region along the
axes of the scan's frame: the Argoverse 2 city frame (the logs here drive at -32 and 19 deg to it) or the nuScenes
LIDAR_TOP frame, whose y axis points forward (the street runs along y). `violation_anatomy.py` finds the growth above
a cut drawn as thin walls along the grid axes. This runs `hgca eval-real` (coarse, k = 3, cut 2 m; the eval-real
defaults otherwise) on each real fixture with the region turned to the vehicle heading of its first frame, and puts
the rows beside those of baseline eval-real JSONs (the region along the frame's axes) given with --baseline.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
# The forward axis of a scan's own frame: AV2 sweeps are in the ego frame (x forward), a nuScenes LIDAR_TOP sweep in
# the sensor frame (x right, y forward)
FORWARD = {"av2": np.array([1.0, 0.0, 0.0]), "nuscenes": np.array([0.0, 1.0, 0.0])}


def heading_deg(item: dict) -> float:
    """Yaw (degrees, about +z in the frame the input is read in) of the vehicle's forward axis at its first frame."""
    from hgca_core.io.sequence import is_sequence, open_sequence, select

    if is_sequence([item["path"]]):
        seq = open_sequence(item["path"], None)
        _, mats = select(seq, item["frames"] or ":")
        forward = np.asarray(mats[0])[:3, :3] @ FORWARD[seq.layout]
    elif item["path"].endswith(".pcd.bin"):
        forward = FORWARD["nuscenes"]
    else:
        raise SystemExit(f"no known forward axis for {item['path']}")
    return float(np.degrees(np.arctan2(forward[1], forward[0])))


def run_turned(item: dict, yaw_deg: float, out: Path, threads: int) -> dict:
    """`hgca eval-real --yaw yaw_deg` on one input: the default region turned by `yaw_deg`."""
    from hgca_core.cli import main

    extra = (["--frames", item["frames"]] if item["frames"] else []) + \
            (["--calibration", item["calibration"]] if item["calibration"] else [])
    code = main(["eval-real", item["path"], *extra, "--threads", str(threads), "--methods", "hgca", "--samples",
                 "3", "--cuts", "2.0", "--no-render", "--yaw", str(yaw_deg), "--out", str(out)])
    if code:
        raise SystemExit(code)
    return next(iter(json.loads(out.read_text())["inputs"].values()))


def row(entry: dict) -> str:
    """'recall / above-cut share / whole share (%)' of an eval-real input entry (coarse row, means)."""
    full = entry["cases"]["full"]["rows"]["hgca"]["summary"]
    cut = entry["cases"]["cut_2"]["rows"]["hgca"]["summary"]
    return (f"{100 * cut['recall']['mean']:.1f} | {cut['generated_above']['mean']:,.0f} | "
            f"{100 * cut['above_empty_share']['mean']:.1f} | {100 * full['empty_share']['mean']:.1f}")


def main(argv: list[str] | None = None) -> int:
    from hgca_core.commands.eval_real import default_items

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--real-dir", default=str(REPO.parent / "shared" / "fixtures" / "real"))
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--baseline", nargs="*", default=[], help="eval-real JSONs of the same weights, default region")
    p.add_argument("--offset", type=float, default=0.0,
                   help="degrees added to each heading (a tiny offset re-rasterises the same scan: the metric's noise)")
    p.add_argument("--out", required=True, help="JSON file (the table goes beside it as .md)")
    args = p.parse_args(argv)
    out = Path(args.out)
    base = {}   # resolved source path -> (eval-real entry, file name), so runs that named an input differently match
    for f in args.baseline:
        for entry in json.loads(Path(f).read_text())["inputs"].values():
            if "cut_2" in entry["cases"] and "hgca" in entry["cases"]["cut_2"]["rows"]:
                base[str(Path(entry["source"]).resolve())] = (entry, Path(f).name)
    results = {}
    for item in default_items(args.real_dir):
        yaw = heading_deg(item) + args.offset
        entry = run_turned(item, yaw, out.with_name(f"{out.stem}_{item['name']}.json"), args.threads)
        results[item["name"]] = {"heading_deg": round(yaw, 2), "eval_real": entry}
        print(item["name"], yaw, row(entry), file=sys.stderr)
    out.write_text(json.dumps({"inputs": results, "baselines": args.baseline, "offset_deg": args.offset},
                              indent=1) + "\n")
    lines = ["| input | region | 2 m recall (%) | cells above the cut | above the cut in observed empty (%) | "
             "whole input in observed empty (%) |", "|---|---|---:|---:|---:|---:|"]
    for name, r in results.items():
        key = str(Path(r["eval_real"]["source"]).resolve())
        if key in base:
            turned = base[key][0]["region"][6]
            lines.append(f"| {name} | {'frame axes' if not turned else f'turned {turned:g} deg'} ({base[key][1]}) | "
                         f"{row(base[key][0])} |")
        lines.append(f"| {name} | turned to the heading{f' + {args.offset:g}' if args.offset else ''}, "
                     f"{r['heading_deg']:g} deg | {row(r['eval_real'])} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The README's close-up of `make demo`'s road: the bundled example completed with the full stage, meshed three
ways (the old 3 cm shell, one surface not faired, one surface faired: the product), rendered from the same eye
and measured on the example's flat road patches (layers per vertical ray, plane-fit RMS).

Run: python benchmarks/demo_closeup.py [--cache DIR] -> docs/images/demo_full_closeup.png and
benchmarks/results/demo_closeup.{md,json}. Uses mesh_quality's builders (the product's `complete_local` and
`udf_mesh`), seed 0, as `make demo` does.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from mesh_quality import fine_state, ground, mesh_both, mesh_stats  # noqa: E402

from hgca_core.commands.demo import EXAMPLE_DIR  # noqa: E402
from hgca_core.geometry.freespace import ray_origins  # noqa: E402
from hgca_core.geometry.region import Region  # noqa: E402
from hgca_core.io import read_scans  # noqa: E402
from hgca_core.io.poses import load_poses  # noqa: E402
from hgca_core.metrics import flatness  # noqa: E402
from hgca_core.pipeline import load_models  # noqa: E402

LABELS = {"before": "before: 3 cm shell", "unfaired": "one surface, not faired",
          "after": "after: one surface, faired", "light": "after, decimated (what make demo writes)"}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cache", default=None, help="folder to keep the fine-stage result between runs")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--image", default=str(REPO / "docs" / "images" / "demo_full_closeup.png"))
    p.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "demo_closeup"))
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    from PIL import Image, ImageDraw

    from hgca_core.render import render_closeup

    poses = EXAMPLE_DIR / "poses.json"
    scan = read_scans([str(EXAMPLE_DIR / e.file) for e in load_poses(poses)], poses=str(poses))
    region = Region.parse(",".join(str(v) for v in json.loads(poses.read_text())["region"]))
    origins = np.asarray(scan.origins, dtype=np.float64)
    index = ray_origins(origins, scan.attributes, scan.points)
    local, sensors = region.to_local(scan.points), region.to_local(origins)
    models = load_models("full", None, None)
    cells10, z = fine_state(models, local, region, 0, Path(args.cache) if args.cache else None, "demo", sensors,
                            index)
    inside = local[region.contains_local(local)]
    m = mesh_both(models.autoencoder, cells10, z, inside, sensors)
    patches = flatness.flat_patches_from_points(inside, max_rms=0.03)
    result = {"patches": len(patches.corners), "ground": ground(m, patches, {"input": inside}),
              "stats": {k: mesh_stats(m[k]) for k in LABELS}, "timings": m["timings"]}
    # the flat patch nearest to the first sensor, seen from 2.5 m back and 1.6 m up, under a grazing light
    c = patches.corners + patches.size / 2
    k = int(np.argmin(np.linalg.norm(c - sensors[0, :2], axis=1)))
    target = np.r_[c[k], patches.height[k]]
    eye = target + [-2.5, -2.5, 1.6]
    tiles = [render_closeup(m[key], eye, target, size=(480, 320), light=np.array([0.9, 0.25, 0.35]))
             for key in ("before", "unfaired", "light")]
    img = Image.fromarray(np.concatenate(tiles, 1))
    draw = ImageDraw.Draw(img)
    for i, key in enumerate(("before", "unfaired", "light")):
        g = result["ground"][key]
        draw.text((6 + 480 * i, 6), f"{LABELS[key]}: {result['stats'][key]['triangles']:,} triangles",
                  fill=(200, 0, 0) if i == 0 else (160, 90, 0) if i == 1 else (0, 120, 0))
        draw.text((6 + 480 * i, 20), f"road: {100 * g['one_layer']:.1f} % one layer, RMS "
                  f"{1000 * g['rms_mesh']:.1f} mm", fill=(40, 40, 40))
    Path(args.image).parent.mkdir(parents=True, exist_ok=True)
    img.save(args.image)
    out = Path(args.out)
    out.with_suffix(".json").write_text(json.dumps(result, indent=1, default=float))
    rms_in = result["ground"]["after"]["rms_input"]
    lines = [f"`make demo`'s road (the bundled example, full stage, seed 0, shipped weights): "
             f"{result['patches']} flat 2 x 2 m patches (`hgca_core.metrics.flatness`), vertical rays every 10 cm; "
             f"input points' plane-fit RMS {1000 * rms_in:.1f} mm.", "",
             "| mesh | one layer (%) | no layer (%) | 2+ layers (%) | ground RMS (mm) | triangles |",
             "|---|---:|---:|---:|---:|---:|"]
    for key, label in LABELS.items():
        g, st = result["ground"][key], result["stats"][key]
        lines.append(f"| {label} | {100 * g['one_layer']:.1f} | {100 * g['no_layer']:.1f} | "
                     f"{100 * g['two_plus']:.1f} | {1000 * g['rms_mesh']:.1f} | {st['triangles']:,} |")
    lines += ["", f"![close-up]({os.path.relpath(args.image, out.parent)})"]
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""`hgca eval --split test`: the paper's Table 1 for our synthetic data, baselines and models in one table."""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

METHODS = ("input", "poisson", "gca", "hgca", "hgca-full")
DEFAULT_METHODS = ("input", "poisson", "gca", "hgca")


def add_arguments(p: argparse.ArgumentParser) -> None:
    from hgca_core.commands.complete import add_precision_argument

    p.add_argument("--data", default="data/synth", help="dataset folder (hgca synth --split test)")
    p.add_argument("--split", default="test", choices=("val", "test"))
    p.add_argument("--stage", default="coarse", choices=("coarse", "full"),
                   help="full adds the fine stage's rows (hGCA 10 cm voxels and implicit mesh; needs fine weights)")
    p.add_argument("--fine-weights", default=None, help="fine-stage weights (default: the shipped fine.pt)")
    p.add_argument("--t2", type=int, default=None, help="fine steps (default from the weights)")
    add_precision_argument(p)
    p.add_argument("--count", type=int, default=None, help="evaluate only the first N samples")
    p.add_argument("--samples", type=int, default=3, help="completions k per input (min/avg/TMD)")
    p.add_argument("--methods", default=None,
                   help=f"comma list of {', '.join(METHODS)} (default: the coarse ones, plus hgca-full with --stage full)")
    p.add_argument("--t1", type=int, default=None, help="coarse steps (default from the weights)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="write the rows as JSON and the table as .md next to it")
    p.add_argument("--reuse", nargs="+", default=None, metavar="JSON",
                   help="copy rows of earlier `--out` files on the same samples (e.g. the slow Poisson baseline) "
                        "into the table, for methods not run now; a later file's row wins over an earlier one's")


def run(args: argparse.Namespace) -> int:
    import numpy as np
    import torch
    from tqdm import tqdm

    from hgca_core.errors import InputError
    from hgca_core.geometry import coords as cs
    from hgca_core.geometry.voxel import COARSE, FINE
    from hgca_core.geometry.voxel_mesh import voxel_mesh
    from hgca_core.metrics.baselines import input_baseline, poisson_baseline
    from hgca_core.metrics.evaluate import aggregate, evaluate_sample, format_table
    from hgca_core.models.weights import WEIGHTS_DIR, load_coarse, load_fine, shipped
    from hgca_core.models.gca import sample as gca_sample
    from hgca_core.synth.dataset import load_sample
    from hgca_core.training.data import coarse_pair, split_files

    default = DEFAULT_METHODS + (("hgca-full",) if args.stage == "full" else ())
    methods = [m.strip() for m in args.methods.split(",") if m.strip()] if args.methods else list(default)
    unknown = set(methods) - set(METHODS)
    if unknown:
        raise InputError(f"unknown methods {sorted(unknown)}; choose from {', '.join(METHODS)}")
    from hgca_core.nn.conv import gemm_precision, precision_name, resolve_precision

    files = split_files(args.data, args.split)[: args.count]
    gemm_dtype = resolve_precision(args.precision)
    coarse_models = {planner: load_coarse(shipped("coarse" if planner else "coarse-noplanner"))[0]
                     for planner in {m != "gca" for m in methods if m in ("gca", "hgca", "hgca-full")}}
    if "hgca-full" in methods:
        fine_model, autoencoder, _ = load_fine(args.fine_weights)
    rows_of = {m: [m] for m in methods}
    rows_of["hgca-full"] = ["hgca-10cm", "hgca-implicit"]
    results: dict[str, list[dict]] = {r: [] for m in methods for r in rows_of[m]}
    timings: dict[str, list[float]] = {r: [] for m in methods for r in rows_of[m]}
    for path in tqdm(files, desc=f"eval {args.split}", unit="scene"):
        sample = load_sample(path)
        pts = np.asarray(sample["input_points"], dtype=np.float64)
        s0, _, grid = coarse_pair(path)
        chains: dict[tuple[bool, int], tuple[np.ndarray, torch.Tensor, float]] = {}

        def chain(planner: bool, i: int) -> tuple[np.ndarray, torch.Generator, float]:
            """Coarse completion i and its generator as the chain left it, plus the seconds it took when
            an earlier method ran it: hgca and hgca-full share their chains (same weights, same seeds)."""
            borrowed = (planner, i) in chains
            if not borrowed:
                t = time.time()
                gen = torch.Generator().manual_seed(args.seed + i)
                model = coarse_models[planner]
                with gemm_precision(gemm_dtype):
                    occ = gca_sample(model, cs.with_batch(torch.from_numpy(s0)), grid, args.t1 or model.cfg.steps, gen)
                chains[planner, i] = (occ[:, 1:].numpy(), gen.get_state(), time.time() - t)
            occ, state, secs = chains[planner, i]
            gen = torch.Generator()
            gen.set_state(state)
            return occ, gen, secs if borrowed else 0.0

        for m in methods:
            t0 = time.time()
            if m == "input":
                cells, mesh = input_baseline(pts)
                res = evaluate_sample(sample, [mesh], [cells])
            elif m == "poisson":
                res = evaluate_sample(sample, [poisson_baseline(pts, np.asarray(sample["input_origins"]))])
            elif m == "hgca-full":  # one fine run per sample, scored as 10 cm voxels and as the implicit mesh
                from hgca_core.geometry.voxel import downsample
                from hgca_core.models.cgca import decode_mesh, upsample

                grid10 = tuple(int(v) for v in np.round(np.asarray(sample["region"])[3:6] / FINE))
                fine, meshes, t_mesh, t_borrowed = [], [], 0.0, 0.0
                for i in range(args.samples):
                    occ, gen, secs = chain(True, i)
                    t_borrowed += secs
                    with gemm_precision(gemm_dtype):
                        cells10, z = upsample(fine_model, autoencoder, pts, occ, grid10, args.t2, gen)
                    fine.append(cells10.numpy())
                    t1 = time.time()
                    meshes.append(decode_mesh(autoencoder, cells10, z))
                    t_mesh += time.time() - t1
                t_gen = time.time() - t0 - t_mesh + t_borrowed
                vox = [voxel_mesh(c, FINE, lower_corner=-FINE / 2) for c in fine]
                results["hgca-10cm"].append(evaluate_sample(sample, vox, [downsample(c) for c in fine]))
                results["hgca-implicit"].append(evaluate_sample(sample, meshes))
                timings["hgca-10cm"].append(t_gen / args.samples)
                timings["hgca-implicit"].append((t_gen + t_mesh) / args.samples)
                continue
            else:
                runs = [chain(m == "hgca", i) for i in range(args.samples)]
                occ = [r[0] for r in runs]
                t0 -= sum(r[2] for r in runs)
                meshes = [voxel_mesh(o, COARSE, lower_corner=-FINE / 2) for o in occ]
                res = evaluate_sample(sample, meshes, occ)
            timings[m].append((time.time() - t0) / (args.samples if m in ("gca", "hgca") else 1))
            results[m].append(res)
    names = {"input": ("input", "20cm^3 points"), "poisson": ("Poisson (Open3D)", "mesh"),
             "gca": ("GCA (no planner)", "20cm^3"), "hgca": ("hGCA coarse (planner)", "20cm^3"),
             "hgca-10cm": ("hGCA (10 cm voxels)", "10cm^3"), "hgca-implicit": ("hGCA (implicit)", "implicit")}
    rows = {names[r][0]: {**aggregate(results[r]), "representation": names[r][1],
                          "seconds_per_completion": float(np.mean(timings[r]))} for r in results}
    for path in reversed(args.reuse or []):  # rows computed now first in priority, then the later files
        rows = {**reused_rows(path, [p.name for p in files], args.split, args.samples, set(rows)), **rows}
    order = [v[0] for v in names.values()]     # the paper's row order, whichever file a row came from
    rows = dict(sorted(rows.items(), key=lambda kv: order.index(kv[0]) if kv[0] in order else len(order)))
    table = format_table(rows)
    print(table)
    for name, r in rows.items():
        origin = f" (from {r['reused_from']})" if "reused_from" in r else ""
        print(f"{name}: {r['seconds_per_completion']:.1f} s per completion{origin}")
    if args.out:
        out = Path(args.out)
        out.write_text(json.dumps({"split": args.split, "files": [p.name for p in files], "rows": rows,
                                   "samples": args.samples, "t1": args.t1,
                                   "precision": precision_name(gemm_dtype)}, indent=1))
        out.with_suffix(".md").write_text(table + "\n")
        if out.resolve().parent == WEIGHTS_DIR:  # results beside the weights go on the card
            from hgca_core.training.card import write_model_card

            write_model_card()
    return 0


def reused_rows(path: str, files: list[str], split: str, samples: int, skip: set[str]) -> dict:
    """Rows of an earlier eval on exactly the same samples, split and k, minus those computed now."""
    import json

    from hgca_core.errors import InputError

    try:
        old = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read earlier eval results ({exc.__class__.__name__})", path) from exc
    if old.get("files") != files or old.get("split") != split or old.get("samples") != samples:
        raise InputError(f"earlier results are for other samples ({old.get('split')}: {old.get('files')}, "
                         f"k = {old.get('samples')}); rerun those methods instead", path)
    rows = {}
    for name, r in old["rows"].items():
        if name in skip:
            continue
        r = {**r, "reused_from": r.get("reused_from", Path(path).name)}  # keep the first origin
        if "seconds_per_scene" in r and "seconds_per_completion" not in r:  # files from before per-completion times
            r["seconds_per_completion"] = r.pop("seconds_per_scene") / max(1, int(r.get("k", 1)))
        rows[name] = r
    return rows

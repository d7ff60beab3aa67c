"""`hgca eval --split test`: the paper's Table 1 for our synthetic data, baselines and models in one table."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

METHODS = ("input", "poisson", "gca", "hgca", "hgca-full")
DEFAULT_METHODS = ("input", "poisson", "gca", "hgca")


def add_arguments(p: argparse.ArgumentParser) -> None:
    from hgca_core.commands.arguments import (add_config_arguments, add_methods_argument, add_noplanner_argument,
                                              add_out_argument, counted)

    p.add_argument("--data", default="data/synth", help="dataset folder (hgca synth --split test)")
    p.add_argument("--split", default="test", choices=("val", "test"), help="the split to score (default test)")
    add_config_arguments(p, ("stage", "weights", "fine_weights", "t1", "t2", "precision"),
                         stage={"help": "full adds the fine stage's rows (hGCA 10 cm voxels and implicit mesh; needs "
                                        "fine weights) to the coarse ones"})
    add_noplanner_argument(p)
    p.add_argument("--count", type=counted(1), default=None, help="evaluate only the first N samples")
    add_config_arguments(p, ("samples",), samples={"default": 3, "help": "completions k per input (min/avg/TMD)"})
    add_methods_argument(p, METHODS, None, " (default: the coarse ones, plus hgca-full with --stage full)")
    add_config_arguments(p, ("seed", "free_space"), seed={"help": "sample i of every input uses seed + i"})
    add_out_argument(p, "FILE.json", default=None, help="write the rows as JSON and the table as .md next to it")
    p.add_argument("--render", default=None, metavar="PNG",
                   help="also write a PNG of the first scene: its ground truth, input and each row's first "
                        "completion from one viewpoint (grey where the input lies, blue where it was generated)")
    p.add_argument("--reuse", nargs="+", default=None, metavar="JSON",
                   help="copy rows of earlier `--out` files on the same samples (e.g. the slow Poisson baseline) "
                        "into the table, for methods not run now; a later file's row wins over an earlier one's")


def run(args: argparse.Namespace) -> int:
    import numpy as np
    from tqdm import tqdm

    from hgca_core.errors import InputError
    from hgca_core.metrics.evaluate import aggregate, format_table
    from hgca_core.config import CompletionConfig
    from hgca_core.metrics.synthetic import evaluate_methods, load_method_models
    from hgca_core.models.weights import WEIGHTS_DIR, weights_record
    from hgca_core.nn.conv import precision_name, resolve_precision
    from hgca_core.dataset.packed import refuse_packed
    from hgca_core.dataset.samples import split_files

    default = DEFAULT_METHODS + (("hgca-full",) if args.stage == "full" else ())
    methods = [m.strip() for m in args.methods.split(",") if m.strip()] if args.methods else list(default)
    unknown = set(methods) - set(METHODS)
    if unknown:
        raise InputError(f"unknown methods {sorted(unknown)}; choose from {', '.join(METHODS)}")
    if args.render and Path(args.render).suffix.lower() != ".png":
        raise InputError(f"--render writes a PNG, not {Path(args.render).suffix or 'a file without suffix'}",
                         args.render)
    check_eval_outputs(args)
    files = split_files(args.data, args.split)[: args.count]
    refuse_packed(files, "hgca eval")
    gemm_dtype = resolve_precision(args.precision)
    rows_of = {m: list(ROWS_OF.get(m, (m,))) for m in methods}
    computed = {ROW_NAMES[r][0] for m in methods for r in rows_of[m]}
    record = weights_record(methods, args.weights, args.fine_weights, args.noplanner_weights)
    reused: dict = {}
    for path in reversed(args.reuse or []):  # read and checked before any scene runs: a bad file costs nothing
        old_rows, old_record = reused_rows(path, [p.name for p in files], args.split, args.samples,
                                           computed | set(reused))
        record = merge_weights(record, old_record, path)
        reused = {**old_rows, **reused}      # the later files first in priority, as given
    models = load_method_models(methods, args.fine_weights, args.weights, args.noplanner_weights)
    settings = CompletionConfig(samples=args.samples, seed=args.seed, t1=args.t1, t2=args.t2,
                                precision=args.precision, free_space=args.free_space)
    results: dict[str, list[dict]] = {r: [] for m in methods for r in rows_of[m]}
    timings: dict[str, list[float]] = {r: [] for m in methods for r in rows_of[m]}
    kept: dict = {}        # the first scene's first completion per row, for --render
    for i, path in enumerate(tqdm(files, desc=f"eval {args.split}", unit="scene")):
        for row, (res, secs) in evaluate_methods(path, methods, models, settings,
                                                 kept if args.render and i == 0 else None).items():
            results[row].append(res)
            timings[row].append(secs)
    rows = {ROW_NAMES[r][0]: {**aggregate(results[r]), "representation": ROW_NAMES[r][1],
                              "seconds_per_completion": float(np.mean(timings[r]))} for r in results}
    rows = {**reused, **rows}                  # rows computed now first in priority, then the reused files'
    order = [v[0] for v in ROW_NAMES.values()]   # the paper's row order, whichever file a row came from
    rows = dict(sorted(rows.items(), key=lambda kv: order.index(kv[0]) if kv[0] in order else len(order)))
    table = format_table(rows)
    print(table)
    for name, r in rows.items():
        origin = f" (from {r['reused_from']})" if "reused_from" in r else ""
        print(f"{name}: {r['seconds_per_completion']:.1f} s per completion{origin}")
    if args.out:
        out = Path(args.out)
        out.write_text(json.dumps({"data": str(args.data), "split": args.split, "files": [p.name for p in files],
                                   "rows": rows,
                                   "samples": args.samples, "t1": args.t1, "free_space": args.free_space,
                                   **record,
                                   "precision": precision_name(gemm_dtype)}, indent=1))
        out.with_suffix(".md").write_text(table + "\n")
    if args.render and files:   # after the results are written: a rendering never costs the table
        render_scene(files[0], [(ROW_NAMES[r][0], m) for r, m in kept.items()], args.render, args.seed)
        print(f"rendering of {files[0].name}: {args.render}")
    if args.out and Path(args.out).resolve().parent == WEIGHTS_DIR:  # results beside the weights go on the card
        from hgca_core.training.card import write_model_card

        write_model_card()   # after the rendering, which the card shows when it lies beside the table
    return 0


def check_eval_outputs(args: argparse.Namespace) -> None:
    """--out (its .json and .md) and --render pass the one output check, against the data, weights and the
    --reuse files, before any scene runs; the seeds of the k samples fit in 64 bits."""
    from hgca_core.commands.arguments import check_seed_span
    from hgca_core.io.paths import check_outputs

    check_seed_span(args.seed, args.samples)
    outputs = []
    if args.out:
        out = Path(args.out)
        outputs += [out, out.with_suffix(".md")]
    if args.render:
        outputs.append(Path(args.render))
    if outputs:
        check_outputs(outputs, [args.data, args.weights, args.fine_weights, args.noplanner_weights,
                                *(p for p in (args.reuse or []) if not args.out or Path(p) != Path(args.out))])


def render_scene(path: Path, rows: list[tuple[str, "trimesh.Trimesh"]], png: str | Path, seed: int = 0) -> None:
    """One PNG of a test scene: the ground-truth surface, the input points, then each row's mesh, all from one
    viewpoint above the street's near side; meshes grey where they meet the input points, turning blue up to 50 cm
    away (the colouring of `hgca complete`'s previews and the Blender material)."""
    import numpy as np
    import trimesh

    from hgca_core.geometry.nearest import PointIndex
    from hgca_core.geometry.region import Region
    from hgca_core.render import gallery, mesh_image
    from hgca_core.dataset.samples import load_sample

    sample = load_sample(path)
    size = Region.from_tuple(sample["region"]).size
    ground = float(np.asarray(sample["ground_z"]))
    pts = np.asarray(sample["input_points"], dtype=np.float64)
    target = np.array([size[0] / 2, size[1] / 2, ground + 2.0])
    eye = target + np.array([-0.4, -0.62, 0.45]) * float(np.linalg.norm(size[:2]))
    view = dict(size=(640, 420), eye=eye, target=target, samples=600_000, seed=seed)
    empty = trimesh.Trimesh()
    panels = [("ground truth", mesh_image(empty, np.asarray(sample["gt_surface"]), point_rgb=(110.0, 110.0, 110.0),
                                          **view)),
              (f"input ({len(pts):,} points)", mesh_image(empty, pts, **view))]
    index = PointIndex(pts)
    for name, mesh in rows:
        if name == "input":
            continue
        # a 20 cm cell's corners lie up to 35 cm from the points inside it: grey to 20 cm, full blue from 50 cm
        near = (np.clip(index.distances(np.asarray(mesh.vertices)) - 0.2, 0.0, 0.3) / 0.6
                if len(mesh.vertices) else None)
        panels.append((name, mesh_image(mesh, colour_by=near, **view)))
    title = f"{path.parent.parent.name}/{path.parent.name}/{path.name}, sample seed {seed}"
    gallery(panels, png, columns=4, title=title)


# row key -> (table name, representation); the weights a row runs are its method's (`weights.weights_files`)
ROW_NAMES = {"input": ("input", "20cm^3 points"), "poisson": ("Poisson (Open3D)", "mesh"),
             "gca": ("GCA (no planner)", "20cm^3"), "hgca": ("hGCA coarse (planner)", "20cm^3"),
             "hgca-10cm": ("hGCA (10 cm voxels)", "10cm^3"), "hgca-implicit": ("hGCA (implicit)", "implicit")}
ROWS_OF = {"hgca-full": ("hgca-10cm", "hgca-implicit")}   # a method's rows; any other method is its one row
LEGACY_ROLES = {"hgca": "coarse", "gca": "noplanner"}   # results files before roles named weights by method


def merge_weights(record: dict, old: dict, path: str) -> dict:
    """The weights record of a table with reused rows: each role once, the run's own or the reused file's. A role
    the reused rows ran with other weights (another digest) than this run is refused: the table would mix two
    models under one name."""
    from hgca_core.errors import InputError

    files, digests = dict(record["weights"]), dict(record["weights_sha256"])
    for role, f in old["weights"].items():
        was = old["weights_sha256"].get(role)
        if role not in files:
            files[role] = f
            if was:
                digests[role] = was
        elif was and digests.get(role) and was != digests[role]:
            raise InputError(f"the reused rows ran other {role} weights (sha256 {was[:12]}, {f}) than this run "
                             f"(sha256 {digests[role][:12]}, {files[role]}): rerun those rows with these weights, "
                             "or reuse a file made with them", path)
    return {"weights": files, "weights_sha256": digests}


def reused_rows(path: str, files: list[str], split: str, samples: int, skip: set[str]) -> tuple[dict, dict]:
    """Rows of an earlier eval on exactly the same samples, split and k, minus those computed now, and the
    weights record ({"weights", "weights_sha256"} by role) of the roles those rows ran."""
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
    from hgca_core.models.weights import weights_files

    method = {name: next((m for m, rs in ROWS_OF.items() if key in rs), key) for key, (name, _) in ROW_NAMES.items()}
    roles = set(weights_files([method[name] for name in rows if name in method]))   # the one role table
    named = old.get("weights") if isinstance(old.get("weights"), dict) else {}
    named = {LEGACY_ROLES.get(k, k): v for k, v in named.items()}
    digests = old.get("weights_sha256") if isinstance(old.get("weights_sha256"), dict) else {}
    return rows, {"weights": {r: f for r, f in named.items() if r in roles},
                  "weights_sha256": {r: d for r, d in digests.items() if r in roles}}

"""The coarse model's last-step threshold (`GCAConfig.keep`) on val sweeps and on the real logs (run by hand):
`python benchmarks/keep_sweep.py --keeps 0.5,0.6,0.7 --out benchmarks/results/keep_sweep.json`.

Why: the last transition keeps the cells with p > keep. At 0.5 (the most likely state, as the paper) the model
keeps far cells it is unsure of, and on real sensors many of those lie where the rays saw empty space
(`violation_anatomy.py`). The chain before the last step is the same at every threshold (same seed, same draws),
so each higher threshold keeps a subset of the cells of a lower one: a pure precision / recall trade, chosen here
on the synthetic val sweeps and the real AV2 logs (nuScenes is reported, not chosen on). For each threshold a copy
of the weights with that `keep` is written and scored by `benchmarks/val_cut.py` (val sweeps, cut 2 m) and
`hgca eval-real` (coarse stage, k = 3, cuts 2 m and 1.5 m); the table goes beside the JSON (.md).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import val_cut  # benchmarks reuse each other's helpers
from paired_eval import standard_error

REPO = Path(__file__).resolve().parents[1]


def variant(weights: str | None, keep: float, folder: Path, field: str = "keep") -> Path:
    """A copy of the coarse weights whose config holds `field` = `keep` (tensors and the rest of the file unchanged):
    the last-step threshold `keep` or the every-step logit shift `bias` (`GCAConfig`)."""
    from hgca_core.models.weights import load_file, save_file, shipped

    blob = load_file(weights or shipped("coarse"))
    blob["config"] = {**blob["config"], field: keep}
    return save_file(blob, folder / f"coarse_{field}{keep:g}.pt")


def jobs(w: Path, tag: str, folder: Path, data: str, samples: int) -> list[list[str]]:
    """The two scoring commands of one weights file: val sweeps, then the real logs."""
    val = val_cut.command(w, folder / f"val_{tag}.json", data, samples)
    real = [*val_cut.CLI, "eval-real", "--threads", "1", "--methods", "hgca", "--samples", str(samples), "--cuts",
            "2.0,1.5", "--no-render", "--weights", str(w), "--out", str(folder / f"real_{tag}.json")]
    return [val, real]


def run_all(cmds: list[list[str]], n: int) -> bool:
    """The scoring commands, n at a time; False (exit codes on stderr) when one of them failed."""
    with ThreadPoolExecutor(n) as pool:
        codes = list(pool.map(lambda c: subprocess.run(c, check=False, stdout=subprocess.DEVNULL).returncode, cmds))
    if any(codes):
        print(f"a scoring command failed (exit codes {codes})", file=sys.stderr)
    return not any(codes)


def scored(folder: Path, tag: str) -> dict:
    """`scores` of the two result files `jobs` wrote for `tag`."""
    return scores(json.loads((folder / f"val_{tag}.json").read_text()),
                  json.loads((folder / f"real_{tag}.json").read_text()))


def known_rows(items: list[str]) -> dict[str, dict]:
    """`scores` of rows scored before by val_cut.py and `hgca eval-real`, each given as LABEL=VAL.json,REAL.json;
    either may be A.json+B.json, runs of the same weights with other seeds (`pooled`). Either may be left out,
    not both: LABEL=,REAL.json for weights scored on the real logs only, LABEL=VAL.json, for weights the val
    sweeps screened out before the real logs' slower scoring."""
    none = {"inputs": {}}
    return {label: scores(pooled(val) if val else none, pooled(real) if real else none)
            for label, val, real in map(_row, items)}


def _row(item: str) -> tuple[str, str, str]:
    """(label, val spec, real spec) of one LABEL=VAL.json,REAL.json; ValueError when it is not one."""
    label, _, files = item.rpartition("=")
    val, comma, real = files.partition(",")
    if not label or not comma or not (val or real):
        raise ValueError(f"{item!r}: expected LABEL=VAL.json,REAL.json (either may be left out, not both)")
    return label, val, real


def row_files(items: list[str]) -> list[str]:
    """Every results file the rows `known_rows` reads name, pooled ones each on its own."""
    return [f for item in items for spec in _row(item)[1:] if spec for f in spec.split("+")]


def resummarised(doc: dict, samples_of) -> dict:
    """A copy of an `hgca eval-real` / val_cut.py result whose every row holds `samples_of((input, case, method),
    row)` as its per-sample scores, its k and summary recomputed from them; a row given no samples keeps its own
    (a row without per-sample scores keeps its summary)."""
    from hgca_core.metrics.realscan import summarise

    out = json.loads(json.dumps(doc))
    for name, res in out["inputs"].items():
        for case, c in res["cases"].items():
            for method, row in c["rows"].items():
                samples = samples_of((name, case, method), row)
                if samples:
                    row.update(per_sample=samples, k=len(samples), summary=summarise(samples))
    return out


def pooled(spec: str) -> dict:
    """One results file, or several joined by '+': runs of the same command on the same weights with disjoint
    seeds (`--seed 0 --samples 6`, then `--seed 6 --samples 6`), read as one run of all their samples, every
    summary recomputed over the pooled per-sample scores. Why: a real log's above-cut share swings several points
    between samples, so telling weights apart takes more samples than one scoring run affords."""
    paths = spec.split("+")
    docs = [json.loads(Path(p).read_text()) for p in paths]
    if len(docs) == 1:
        return docs[0]
    first = docs[0]
    # what may differ between runs that pool: not the weights' digests (`weights_sha256`), only where they lay
    free = ("seed", "samples", "full_samples", "threads", "weights")

    def command(d: dict) -> dict:
        return {k: v for k, v in d.get("config", {}).items() if k not in free}

    ranges = []
    for path, d in zip(paths, docs):
        cfg = d.get("config", {})
        if command(d) != command(first) or set(d["inputs"]) != set(first["inputs"]):
            raise ValueError(f"{path}: not the same command on the same inputs as {paths[0]}; cannot pool")
        ranges.append((int(cfg.get("seed", 0)), int(cfg.get("seed", 0)) + int(cfg.get("samples", 0))))
    ranges.sort()
    if any(a[1] > b[0] for a, b in zip(ranges, ranges[1:])):
        raise ValueError(f"{spec}: the runs' seeds overlap ({ranges}), so pooling would count samples twice")

    def joined(path: tuple[str, str, str], row: dict) -> list[dict]:
        name, case, method = path
        return [s for d in docs for s in d["inputs"][name]["cases"][case]["rows"][method].get("per_sample", [])]

    out = resummarised(first, joined)
    out["config"] = {**first.get("config", {}), "seeds": [list(r) for r in ranges],
                     "samples": sum(b - a for a, b in ranges)}
    return out


def mean(summary: dict, key: str) -> float:
    return float(summary[key]["mean"])


def scores(val: dict, real: dict) -> dict:
    """Per input: the whole sweep's share in observed empty space; per cut: recall, cells above, share there."""
    out = {}
    for name, res in [*(("val/" + k, v) for k, v in val["inputs"].items()), *real["inputs"].items()]:
        row = {"whole_empty_share": mean(res["cases"]["full"]["rows"]["hgca"]["summary"], "empty_share")}
        for case, c in res["cases"].items():
            if case.startswith("cut_"):
                s = c["rows"]["hgca"]["summary"]
                samples = c["rows"]["hgca"].get("per_sample", [])
                # a sample that grew nothing above the cut has no share (None); the summary's mean skips it too
                shares = [p["above_empty_share"] for p in samples if p["above_empty_share"] is not None]
                row[case] = {"recall": mean(s, "recall"), "generated_above": mean(s, "generated_above"),
                             "above_empty_share": mean(s, "above_empty_share"), "k": len(samples),
                             # standard error of the mean over the k samples: one sample's share swings by
                             # several points (shipped weights on AV2 7fab: 5.1-10.4 %, recipe_s31.md)
                             "above_empty_sem": standard_error(shares) if len(shares) > 1 else None}
        out[name] = row
    return out


def header(info: dict) -> str:
    """What was scored, on what: the weights, the val data's generator version, the machine."""
    what = (f"Coarse weights {info['weights']} with `{info.get('field', 'keep')}` replaced (`GCAConfig`)"
            if info.get("keeps", True) else "Coarse weights scored before by the same commands (rows named by label)")
    return (f"{what}; k = "
            f"{info['samples']}; val: the first sweep of the first 4 val scenes of {info['data']} (generator version "
            f"{info['generator']}), cut 2 m; real: `hgca eval-real` coarse stage. Machine: {info['machine']}, torch "
            f"{info['torch']}, 1 thread per scoring process, precision auto ({info['precision']} here).\n\n")


def table(results: dict[str, dict], label: str = "keep") -> str:
    """Markdown: one row per variant (threshold), val averaged over the sweeps, real per log."""
    lines = [f"| {label} | val: cells above 2 m cut / recall % / above-cut in obs. empty % / whole in obs. empty % "
             "(mean of sweeps) | real 2 m recall % | real above 2 m cut in obs. empty % | real 1.5 m recall % | "
             "real above 1.5 m in obs. empty % | real whole input in obs. empty % |", "|---|---|---|---|---|---|---|"]
    for keep, sc in results.items():
        val = [v for k, v in sc.items() if k.startswith("val/")]
        real = {k: v for k, v in sc.items() if not k.startswith("val/")}

        def avg(rows, f):
            return sum(f(r) for r in rows) / len(rows)

        v = (f"{avg(val, lambda r: r['cut_2']['generated_above']):,.0f}"
             f" / {100 * avg(val, lambda r: r['cut_2']['recall']):.1f}"
             f" / {100 * avg(val, lambda r: r['cut_2']['above_empty_share']):.1f}"
             f" / {100 * avg(val, lambda r: r['whole_empty_share']):.1f}")

        def per(f):
            return " / ".join(f"{100 * f(r):.1f}" for r in real.values())

        lines.append(f"| {keep} | {v} | {per(lambda r: r['cut_2']['recall'])} | "
                     f"{per(lambda r: r['cut_2']['above_empty_share'])} | {per(lambda r: r['cut_1.5']['recall'])} | "
                     f"{per(lambda r: r['cut_1.5']['above_empty_share'])} | {per(lambda r: r['whole_empty_share'])} |")
    first = next(iter(results.values()))
    lines.append(f"\nReal logs in order: {', '.join(k for k in first if not k.startswith('val/'))}.")
    return "\n".join(lines) + "\n"


def machine_info(args: argparse.Namespace) -> dict:
    import platform

    import torch

    from hgca_core.nn.conv import precision_name, resolve_precision

    recipe = Path(args.data, "recipe.json")
    generator = json.loads(recipe.read_text()).get("generator_version") if recipe.exists() else None
    cpu = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                if ln.startswith("model name")), platform.machine()) if Path("/proc/cpuinfo").exists() else ""
    return {"weights": args.weights or "shipped coarse.pt", "samples": args.samples, "data": args.data,
            "generator": generator, "machine": f"{cpu}, {os.cpu_count()} cores", "torch": torch.__version__,
            "precision": precision_name(resolve_precision("auto"))}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--weights", default=None, help="coarse weights (default: the shipped coarse.pt)")
    p.add_argument("--field", choices=("keep", "bias"), default="keep",
                   help="the config value to vary: the last-step threshold or the every-step logit shift")
    p.add_argument("--keeps", "--values", dest="keeps", default="0.5,0.6,0.7",
                   help="comma list of values (thresholds in (0, 1), or logit shifts); empty: only --known rows")
    p.add_argument("--known", action="append", default=[], metavar="LABEL=VAL.json,REAL.json",
                   help="a row scored before by val_cut.py and hgca eval-real, e.g. other weights (repeatable)")
    p.add_argument("--data", default=str(REPO / "data" / "synth2"), help="dataset folder with a val split")
    p.add_argument("--samples", type=int, default=3)
    p.add_argument("--jobs", type=int, default=2, help="scoring processes at once (1 thread each)")
    p.add_argument("--out", required=True, help="results JSON (the table goes to .md beside it)")
    args = p.parse_args(argv)
    keeps = [float(k) for k in args.keeps.split(",")] if args.keeps else []
    if not keeps and not args.known:
        p.error("nothing to score: give --keeps or --known")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        cmds = [c for k in keeps for c in jobs(variant(args.weights, k, folder, args.field), f"{k:g}", folder,
                                               args.data, args.samples)]
        if not run_all(cmds, args.jobs):
            return 1
        results = {**known_rows(args.known), **{f"{k:g}": scored(folder, f"{k:g}") for k in keeps}}
    out = Path(args.out)
    info = {**machine_info(args), "field": args.field, "keeps": keeps}
    out.write_text(json.dumps({**info, "known": args.known, "results": results}, indent=1))
    out.with_suffix(".md").write_text(header(info) + table(results, label=args.field if keeps else "weights"))
    print(out.with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Paired quality check of faster step counts: does a configuration with fewer GCA steps (t1 coarse, t2 fine)
score as the default does, within the default's own seed-to-seed noise?

    python benchmarks/quality_check.py synth --t1 30 --t2 15 --seed 0     # one configuration's completions
    python benchmarks/quality_check.py real --t1 30 --seed 0              # the real-scan benchmark's
    python benchmarks/quality_check.py page                               # the results page from the cache

Every completion is scored per scene and cached on disk (runs/quality/), so a rerun only scores what is missing
and the page is built from the cache. The synthetic test split is scored by `hgca eval`'s own code
(`metrics.synthetic.evaluate_methods`: IoU, ReSim, Street CD of the coarse 20 cm cells and the fine implicit
mesh); the real scans by `hgca eval-real` (recall of the cells cut away 2 m above the ground, generated cells in
the observed free space, its core and swept cells). Pairs are per scene: the same input, the same seed, only the
step counts differ; the noise floor pairs the default with itself at another seed.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "data" / "synth2f" / "test"
CACHE = REPO / "runs" / "quality"
RESULTS = REPO / "benchmarks" / "results"


def tag(t1: int | None, t2: int | None, seed: int) -> str:
    """The cache folder's name of one configuration (None: the weights' own step count)."""
    return f"t1_{t1 or 'w'}_t2_{t2 or 'w'}_s{seed}"


def cpu_seconds() -> float:
    """This process's user + system CPU seconds so far."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def run_synth(t1: int | None, t2: int | None, seed: int, count: int | None, reverse: bool = False,
              scenes: list[str] | None = None, folder: Path | None = None) -> None:
    """Complete (full stage, k = 1) and score each test scene missing from the cache of this configuration
    (`reverse`: last scene first, so a second process on the same configuration works from the other end;
    `scenes`: only these, by name, so that processes can share out the missing scenes; `folder`: another cache)."""
    import torch

    from hgca_core.metrics.settings import EvalSettings
    from hgca_core.metrics.synthetic import evaluate_methods, load_method_models

    torch.set_num_threads(1)
    folder = folder or CACHE / "synth" / tag(t1, t2, seed)
    folder.mkdir(parents=True, exist_ok=True)
    files = sorted(DATA.glob("sample_*.npz"))[:count][:: -1 if reverse else 1]
    files = [f for f in files if scenes is None or f.stem in scenes or f.name in scenes]
    models = None
    settings = EvalSettings(samples=1, seed=seed, t1=t1, t2=t2, precision="fp32", free_space="auto")
    for path in files:
        out = folder / f"{path.stem}.json"
        if out.exists():
            continue
        models = models or load_method_models(["hgca", "hgca-full"], None)
        c0, w0 = cpu_seconds(), time.perf_counter()
        rows = evaluate_methods(path, ["hgca", "hgca-full"], models, settings)
        cpu, wall = cpu_seconds() - c0, time.perf_counter() - w0
        keep = {row: {"metrics": {k: v for k, v in res.items() if not isinstance(v, list)}, "seconds": secs}
                for row, (res, secs) in rows.items()}
        out.write_text(json.dumps({"scene": path.name, "t1": t1, "t2": t2, "seed": seed, "rows": keep,
                                   "cpu_seconds": cpu, "wall_seconds": wall,
                                   "load": os.getloadavg()[0]}, indent=1))
        print(f"{folder.name} {path.name}: {wall:.0f} s wall, {cpu:.0f} s CPU", flush=True)


def recheck(t1: int | None, t2: int | None, seed: int, scenes: list[str]) -> None:
    """Complete cached scenes again with the code as it is now (into runs/quality/recheck/) and print whether each
    metric is the same as the cached one: the cache may hold completions of earlier code, which pair with today's
    only if the two give the same scores."""
    folder = CACHE / "recheck" / tag(t1, t2, seed)
    run_synth(t1, t2, seed, None, scenes=scenes, folder=folder)
    for name, diff in recheck_diffs().get(tag(t1, t2, seed), {}).items():
        print(f"{tag(t1, t2, seed)} {name}: largest |difference| of a metric {diff:.3g}", flush=True)


def recheck_diffs() -> dict[str, dict[str, float]]:
    """{configuration: {scene: the largest |difference| of a scored metric between the recheck and the cache}}."""
    out: dict[str, dict[str, float]] = {}
    for f in sorted((CACHE / "recheck").glob("t1_*/sample_*.json")):
        cached = CACHE / "synth" / f.parent.name / f.name
        if not cached.exists():
            continue
        a, b = json.loads(f.read_text())["rows"], json.loads(cached.read_text())["rows"]
        pairs = [(a[row]["metrics"][key], b[row]["metrics"][key], SCALE[key]) for row, key, _, _ in SYNTH_METRICS]
        diffs = [0.0 if x == y or (math.isnan(x) and math.isnan(y)) else abs(x - y) * k for x, y, k in pairs]
        out.setdefault(f.parent.name, {})[f.stem] = max(diffs)
    return out


def run_real(t1: int | None, t2: int | None, seed: int, samples: int, stage: str) -> None:
    """`hgca eval-real` of the three real fixtures at this configuration (cut 2 m), resumable."""
    folder = CACHE / "real"
    folder.mkdir(parents=True, exist_ok=True)
    out = folder / f"{tag(t1, t2, seed)}_{stage}_k{samples}.json"
    cmd = [sys.executable, "-m", "hgca_core.cli", "eval-real", "--threads", "1", "--methods",
           "hgca-full" if stage == "full" else "hgca", "--samples", str(samples), "--cuts", "2.0",
           "--full-cuts", "2.0", "--seed", str(seed), "--no-render", "--resume", "-o", str(out)]
    cmd += ["--t1", str(t1)] if t1 else []
    cmd += ["--t2", str(t2)] if t2 else []
    c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    w0 = time.perf_counter()
    subprocess.run(cmd, check=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    log = folder / f"{out.stem}.time.json"
    prev = json.loads(log.read_text()) if log.exists() else {"cpu_seconds": 0.0, "wall_seconds": 0.0}
    log.write_text(json.dumps({"cpu_seconds": prev["cpu_seconds"] + c1.ru_utime + c1.ru_stime - c0.ru_utime
                               - c0.ru_stime, "wall_seconds": prev["wall_seconds"] + time.perf_counter() - w0}))


# (row, metric key, name, better): the synthetic split's scores of one full completion per scene
SYNTH_METRICS = [("hgca", "iou", "IoU 20 cm (%)", "up"), ("hgca", "resim_avg", "ReSim 20 cm (x10 m)", "down"),
                 ("hgca", "street_cd_avg", "Street CD 20 cm (x10 m)", "down"),
                 ("hgca-10cm", "iou", "IoU 10 cm (%)", "up"), ("hgca-implicit", "resim_avg", "ReSim mesh (x10 m)", "down"),
                 ("hgca-implicit", "street_cd_avg", "Street CD mesh (x10 m)", "down")]
SCALE = {"iou": 100.0, "resim_avg": 10.0, "street_cd_avg": 10.0}
# (case, key, name, better): the real-scan benchmark's scores of the coarse stage (k = 1 per input)
REAL_METRICS = [("cut_2", "recall", "real: recall of cut-away cells (%)", "up"),
                ("cut_2", "above_empty_share", "real: above cut in observed empty (%)", "down"),
                ("cut_2", "above_swept_share", "real: above cut, swept (%)", "down"),
                ("full", "empty_share", "real: generated in observed empty (%)", "down"),
                ("full", "core_share", "real: generated in its core (%)", "down"),
                ("full", "swept_share", "real: generated in swept cells (%)", "down")]


def synth_scores(folder: Path, scenes: set[str] | None = None) -> tuple[dict[str, dict[str, float]], dict[str, float]]:
    """{metric name: {scene: value}} of one configuration's cached scenes (those in `scenes` when given), and its
    mean seconds per scene."""
    out: dict[str, dict[str, float]] = {m[2]: {} for m in SYNTH_METRICS}
    wall, cpu = [], []
    for f in sorted(folder.glob("sample_*.json")):
        if scenes is not None and f.stem not in scenes:
            continue
        d = json.loads(f.read_text())
        for row, key, name, _ in SYNTH_METRICS:
            out[name][d["scene"]] = d["rows"][row]["metrics"][key] * SCALE[key]
        wall.append(d["rows"]["hgca-implicit"]["seconds"])
        cpu.append(d["cpu_seconds"])
    n = max(len(wall), 1)
    return out, {"wall_s": sum(wall) / n, "cpu_s": sum(cpu) / n, "scenes": len(wall)}


def real_scores(path: Path) -> tuple[dict[str, dict[str, float]], dict[str, float]]:
    """{metric name: {input: value}} of one `hgca eval-real` result (sample 0 of each input), and its seconds."""
    out: dict[str, dict[str, float]] = {m[2]: {} for m in REAL_METRICS}
    if not path.exists():
        return out, {}
    d = json.loads(path.read_text())
    secs = []
    for name_in, item in d["inputs"].items():
        for case, key, name, _ in REAL_METRICS:
            row = item.get("cases", {}).get(case, {}).get("rows", {}).get("hgca")
            if row:
                out[name][name_in] = 100.0 * row["per_sample"][0][key]
                if key == "recall":
                    secs.append(row["seconds_per_completion"])
    return out, {"wall_s": sum(secs) / len(secs)} if secs else {}


def paired(a: dict[str, float], b: dict[str, float]) -> list[float]:
    """b - a on the scenes both hold (NaN-free)."""
    return [b[k] - a[k] for k in sorted(set(a) & set(b)) if math.isfinite(a[k]) and math.isfinite(b[k])]


def verdict(diffs: list[float], noise: list[float], better: str) -> dict:
    """The decision for one metric. Under "the faster configuration is just another draw of the default", the
    paired differences look like the seed-to-seed ones, whose mean over N scenes has the spread RMS(noise)/sqrt(N)
    (their expected mean is 0). Equal quality (no worse): the mean paired difference in the metric's worse
    direction is at most 2 RMS(noise)/sqrt(N); a gain beyond the band is reported, not held against it."""
    n = len(noise)
    rms = math.sqrt(sum(x * x for x in noise) / n) if n else float("nan")
    band = 2 * rms / math.sqrt(len(diffs)) if n and diffs else float("nan")   # the spread of a mean of len(diffs)
    mean = sum(diffs) / len(diffs) if diffs else float("nan")
    worse = -mean if better == "up" else mean
    return {"beyond_band": abs(mean) > band + 1e-12, "mean_diff": mean, "band": band, "max_seed_noise": max((abs(x) for x in noise), default=float("nan")),
            "mean_seed_diff": sum(noise) / n if n else float("nan"), "pairs": len(diffs),
            "equal": bool(diffs) and n > 0 and worse <= band + 1e-12}


def collect(default: str, noise_seed: int) -> dict:
    """Every cached configuration against the default (seed 0), with the default's seed noise."""
    t1d, t2d = (int(v) for v in default.split(","))
    folders = sorted((CACHE / "synth").glob("t1_*_s0")) + [CACHE / "synth" / tag(t1d, t2d, noise_seed)]
    # the scenes every configuration and the noise run hold: means and seconds on one set of scenes
    common = set.intersection(*({f.stem for f in d.glob("sample_*.json")} for d in folders))
    base, _ = synth_scores(CACHE / "synth" / tag(t1d, t2d, 0), common)
    noise, _ = synth_scores(CACHE / "synth" / tag(t1d, t2d, noise_seed), common)
    rbase, _ = real_scores(CACHE / "real" / f"{tag(t1d, t2d, 0)}_coarse_k1.json")
    rnoise, _ = real_scores(CACHE / "real" / f"{tag(t1d, t2d, noise_seed)}_coarse_k1.json")
    configs = []
    for folder in folders[:-1]:
        t1, t2 = int(folder.name.split("_")[1]), int(folder.name.split("_")[3])
        scores, secs = synth_scores(folder, common)
        real_file = CACHE / "real" / f"{tag(t1, t2d, 0)}_coarse_k1.json"   # the coarse stage: t1 only
        rscores, rsecs = real_scores(real_file)
        metrics = {}
        for _, _, name, better in SYNTH_METRICS:
            metrics[name] = {"mean": _mean(scores[name].values()), "better": better,
                             **verdict(paired(base[name], scores[name]), paired(base[name], noise[name]), better)}
        for _, _, name, better in REAL_METRICS:
            if rscores[name]:
                metrics[name] = {"mean": _mean(rscores[name].values()), "better": better,
                                 **verdict(paired(rbase[name], rscores[name]), paired(rbase[name], rnoise[name]), better)}
        complete = all(name in metrics for _, _, name, _ in REAL_METRICS)
        configs.append({"t1": t1, "t2": t2, "default": (t1, t2) == (t1d, t2d), **secs, "real_scored": complete,
                        "real_coarse_s": rsecs.get("wall_s"), "metrics": metrics,
                        "equal_on_all": all(m["equal"] for m in metrics.values()) if (t1, t2) != (t1d, t2d)
                        else None})
    configs.sort(key=lambda c: (-c["t1"], -c["t2"]))
    return {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "default": [t1d, t2d],
            "noise_seed": noise_seed, "configs": configs, "scenes": sorted(common),
            "data": str(DATA.relative_to(REPO)), "split_scenes": len(list(DATA.glob("sample_*.npz"))),
            "load_average": os.getloadavg()[0], "recheck": recheck_diffs()}


def _mean(values) -> float:
    v = [x for x in values if math.isfinite(x)]
    return sum(v) / len(v) if v else float("nan")


def page(result: dict) -> str:
    """The Markdown page: per configuration and metric the mean, the paired difference to the default and the
    decision, then the seed noise."""
    t1d, t2d = result["default"]
    lines = ["# Fewer GCA steps: paired quality check", "",
             "`python benchmarks/quality_check.py page` (completions cached by its `synth` and `real` commands). "
             f"Default: t1 = {t1d} coarse steps, t2 = {t2d} fine steps (the shipped weights' own). Synthetic test "
             f"split `{result['data']}` ({{n}} scenes): one full completion per scene (k = 1), fp32, 1 thread, scored "
             "by `hgca eval`'s code; real scans: `hgca eval-real --methods hgca --samples 1 --cuts 2.0` (coarse "
             "stage, k = 1) on the three inputs in tests/data/real. Every configuration runs seed 0; the noise "
             f"floor is the default at seed {result['noise_seed']}, paired per scene with the default at seed 0.",
             "",
             "Decision per metric: the paired differences (configuration minus default, same scene and seed) are "
             "set against the seed-to-seed differences of the default. If the faster configuration were just another "
             "draw of the default, the mean of N paired differences would spread like RMS(seed diffs)/sqrt(N); "
             "**equal** (no worse than the default) when the mean paired difference in the metric's worse direction is at "
             "most 2 RMS(seed diffs)/sqrt(N) (the band column; about a 97.5 % one-sided test); a difference beyond "
             "the band in the better direction is marked *better*. The real-scan rows have N = 3 inputs, so their "
             "band is wide. N: the scenes (inputs) a configuration and the default both hold; the band uses the seed "
             "differences of all the scenes the default holds at both seeds.", ""]
    n = max(c.get("scenes", 0) for c in result["configs"])
    base_cpu = next(c["cpu_s"] for c in result["configs"] if c["default"])
    lines[2] = lines[2].replace("{n}", str(n))
    for c in result["configs"]:
        title = f"t1 {c['t1']}, t2 {c['t2']}" + (" (default)" if c["default"] else "")
        verdict_txt = ("" if c["default"] else
                       " — **not** within noise on every metric" if not c["equal_on_all"] else
                       " — equal quality on every metric" if c["real_scored"] else
                       " — equal quality on the synthetic split (real scans not scored)")
        lines += [f"## {title}{verdict_txt}", "",
                  f"Full completion {c['wall_s']:.1f} s wall (pipeline stages), {c['cpu_s']:.1f} s CPU per scene "
                  f"(completion and scoring), mean of {c['scenes']} scenes"
                  + (f"; real coarse completion {c['real_coarse_s']:.1f} s wall." if c.get("real_coarse_s") else "."),
                  "", "| metric | better | mean | paired diff vs default | band (2 RMS/sqrt N) | max seed noise "
                  "| mean seed diff | N | equal |", "|---|---|---:|---:|---:|---:|---:|---:|---|"]
        for name, m in c["metrics"].items():
            lines.append(f"| {name} | {'↑' if m['better'] == 'up' else '↓'} | {m['mean']:.3f} | {m['mean_diff']:+.3f} "
                         f"| {m['band']:.3f} | {m['max_seed_noise']:.3f} | {m['mean_seed_diff']:+.3f} | {m['pairs']} "
                         f"| {('better' if m['beyond_band'] else 'yes') if m['equal'] else 'no'} |")
        lines.append("")
    lines += ["## Reading", ""]
    for c in result["configs"]:
        if c["default"]:
            continue
        worse = [name for name, m in c["metrics"].items() if not m["equal"]]
        lines.append(f"- t1 {c['t1']}, t2 {c['t2']}: {c['cpu_s'] / base_cpu:.2f} of the default's CPU per scene; "
                     + ("worse than the seed noise on " + ", ".join(worse) if worse else
                        "no metric worse than the seed noise") + ".")
    lines += ["", f"Scored so far: {n} of {result['split_scenes']} synthetic scenes held by every configuration "
              f"({', '.join(result['scenes'])}; means and seconds on those). The default "
              "changes only when a faster configuration is within the noise on every metric, on the whole split "
              "and all three real inputs; `synth` and `real` resume from the cache.", ""]
    for config, scenes in result.get("recheck", {}).items():
        worst = max(scenes.values())
        lines += [f"Cache against today's code: {', '.join(sorted(scenes))} at {config} completed again "
                  f"(`quality_check.py recheck`): " + ("every metric the same as the cached row." if worst == 0 else
                                                      f"the largest metric difference is {worst:.3g}."), ""]
    return "\n".join(lines) + "\n"


def plot(result: dict, path: Path) -> None:
    """Quality against time: per configuration the mean paired difference to the default on a few metrics,
    against its CPU seconds per scene; grey: the default's seed-noise band (the worse side is what decides)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = ["Street CD 20 cm (x10 m)", "ReSim mesh (x10 m)", "Street CD mesh (x10 m)",
            "real: recall of cut-away cells (%)"]
    fig, axes = plt.subplots(1, len(keys), figsize=(4 * len(keys), 3.6))
    base = next(c for c in result["configs"] if c["default"])
    for ax, key in zip(axes, keys):
        ax.axhline(0, color="k", lw=0.8)
        for c in result["configs"]:
            m = c["metrics"].get(key)
            if m is None or c["default"]:
                continue
            ax.errorbar(c["cpu_s"], m["mean_diff"], yerr=m["band"], fmt="o", color="#1f77b4" if m["equal"]
                        else "#d62728", ecolor="#bbbbbb", capsize=4)
            ax.annotate(f"{c['t1']}/{c['t2']}", (c["cpu_s"], m["mean_diff"]), fontsize=8, xytext=(5, 3),
                        textcoords="offset points")
        ax.plot(base["cpu_s"], 0, "ks")
        better = base["metrics"].get(key, {}).get("better", "down")
        ax.set_title(f"{key}: diff vs 30/15 ({'higher' if better == 'up' else 'lower'} is better)", fontsize=8)
        ax.set_xlabel("CPU s per scene (completion + scoring)")
    fig.suptitle("fewer steps: mean paired difference to the default (bars: the seed-noise band; red: worse "
                 "beyond it)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    for name in ("synth", "real", "recheck"):
        s = sub.add_parser(name)
        s.add_argument("--t1", type=int, default=None)
        s.add_argument("--t2", type=int, default=None)
        s.add_argument("--seed", type=int, default=0)
        s.add_argument("--count", type=int, default=None)
        s.add_argument("--samples", type=int, default=1)
        s.add_argument("--stage", default="coarse", choices=["coarse", "full"])
        s.add_argument("--reverse", action="store_true", help="synth: the scenes from the last one")
        s.add_argument("--scenes", nargs="+", default=None, help="synth, recheck: only these scenes (sample_2000003 ...)")
    pg = sub.add_parser("page")
    pg.add_argument("--default", default="30,15", help="the default's t1,t2")
    pg.add_argument("--noise-seed", type=int, default=1, help="the default's second seed (the noise floor)")
    args = p.parse_args()
    if args.cmd == "synth":
        run_synth(args.t1, args.t2, args.seed, args.count, args.reverse, args.scenes)
    elif args.cmd == "recheck":
        if not args.scenes:
            p.error("recheck: name the cached scenes to complete again (--scenes)")
        recheck(args.t1, args.t2, args.seed, args.scenes)
    elif args.cmd == "real":
        run_real(args.t1, args.t2, args.seed, args.samples, args.stage)
    else:
        from common import write_page

        result = collect(args.default, args.noise_seed)
        print(write_page(RESULTS, "quality", result, page, plot))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Completion time A/B in fresh processes, interleaved: glibc's allocator as the CLI sets it up against its defaults,
or an earlier revision of the code against this one, on one machine in one sitting.

    python benchmarks/completion_ab.py allocator [--pairs 5] [--stage coarse] [--width W | --input PATH]
    python benchmarks/completion_ab.py base REV [--pairs 3] [--stage coarse] [--width W | --input PATH]

Each run is `hgca bench`'s worker on its default region (38.4 x 38.4 x 8 m, synthetic drive; or a 40 x W m strip) in
its own process, so it pays what a user's one-shot command pays; with `--input PATH` (a scan file or a log folder,
e.g. the real fixtures) each run is `hgca complete PATH --stage S` itself, its peak RSS and page faults read from
the child's own rusage, and the output mesh's sha256 recorded (the sides should make the same mesh). `allocator`:
this tree with `hardware.tune_allocator` ("tuned") and with `HGCA_ALLOCATOR=system` (glibc's defaults). `base REV`:
REV checked out in a temporary git worktree with its own shipped weights, run by this venv, against this tree. Why
interleaved (A B B A A B ...): this VM's speed drifts by up to ~35 % within an hour, so a target such as "no worse
than today" is only answered by the two codes side by side. Reported per side: each run's seconds, minor page faults
(where the worker reports them) and peak RSS, medians, and a PNG of the runs in the order they ran.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from hgca_core.bench import worker  # noqa: E402
from hgca_core.hardware import ALLOCATOR_SWITCH, machine  # noqa: E402
from hgca_core.io.paths import check_outputs  # noqa: E402


@dataclass(frozen=True)
class Side:
    """One arm of the A/B: the code tree it runs and the environment variables it adds."""

    name: str
    tree: Path
    env: tuple[tuple[str, str], ...] = ()

    def environ(self) -> dict:
        env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != ALLOCATOR_SWITCH}
        env.setdefault("OMP_WAIT_POLICY", "PASSIVE")       # as the CLI sets it
        env["PYTHONPATH"] = str(self.tree)
        env.update(dict(self.env))
        return env


def completion_run(side: Side, stage: str, width: float | None = None) -> dict:
    """One bench worker in `side`'s tree on the default region (`width` None) or a 40 x `width` m strip: total and
    stage seconds, minor faults (if reported), peak RSS."""
    w, d = (38.4, 38.4) if width is None else (width, 40.0)
    row = worker({"width": w, "depth": d, "stage": stage, "device": "cpu", "t1": None, "seed": 0},
                 env=side.environ(), cwd=side.tree)
    if "error" in row:
        sys.exit(f"completion_ab.py: bench worker ({side.name}) failed: {row['error']}")
    return {k: row[k] for k in ("seconds", "stages_s", "minor_faults", "peak_rss_gib", "points", "coarse_cells")
            if k in row}


def cli_run(side: Side, stage: str, path: str) -> dict:
    """`hgca complete PATH --stage STAGE` in `side`'s tree: wall seconds, the child's peak RSS and minor faults
    (`os.wait4`: this child's own, not the largest of all children so far), and the mesh's sha256."""
    with tempfile.TemporaryDirectory(prefix="hgca_ab_") as tmp:
        with open(Path(tmp) / "stderr", "w+") as err:
            t = time.perf_counter()
            proc = subprocess.Popen([sys.executable, "-m", "hgca_core.cli", "complete", path, "--stage", stage,
                                     "-o", str(Path(tmp) / "out.ply")], env=side.environ(), cwd=side.tree,
                                    stdout=subprocess.DEVNULL, stderr=err)
            _, status, usage = os.wait4(proc.pid, 0)
            seconds = time.perf_counter() - t
            proc.returncode = os.waitstatus_to_exitcode(status)   # reaped by wait4: Popen must not wait again
            if proc.returncode:
                err.seek(0)
                sys.exit(f"completion_ab.py: hgca complete ({side.name}) failed: {err.read().strip()[-400:]}")
        meshes = sorted(Path(tmp).glob("out*.ply"))
        digest = hashlib.sha256(b"".join(m.read_bytes() for m in meshes)).hexdigest()
    return {"seconds": round(seconds, 2), "minor_faults": usage.ru_minflt,
            "peak_rss_gib": round(usage.ru_maxrss / 2**20, 3), "mesh_sha256": digest}


def alternate(sides: tuple[Side, Side], pairs: int) -> list[Side]:
    """A B B A A B B A ...: each side runs first as often as second."""
    order: list[Side] = []
    for i in range(pairs):
        order += list(sides if i % 2 == 0 else sides[::-1])
    return order


def summary(runs: list[dict], names: tuple[str, str]) -> dict:
    out = {}
    for name in names:
        mine = [r for r in runs if r["side"] == name]
        s = {"runs": len(mine), "median_s": statistics.median(r["seconds"] for r in mine),
             "min_s": min(r["seconds"] for r in mine)}
        if all("minor_faults" in r for r in mine):
            s["median_faults"] = statistics.median(r["minor_faults"] for r in mine)
        if all("peak_rss_gib" in r for r in mine):
            s["median_rss_gib"] = statistics.median(r["peak_rss_gib"] for r in mine)
            s["max_rss_gib"] = max(r["peak_rss_gib"] for r in mine)
        stages = sorted({k for r in mine for k in r.get("stages_s", {})})
        if stages:
            s["median_stages_s"] = {k: statistics.median(r["stages_s"].get(k, 0.0) for r in mine) for k in stages}
        out[name] = s
    return out


def _num(v: float | None, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def table(result: dict) -> str:
    m = result["machine"]
    lines = [f"Completion A/B, {result['title']}", f"Machine: {m['cpu']}, {m['cores']} cores, torch {m['torch']}, "
             f"{m['date']}", ""]
    for what, block in result["blocks"].items():
        names = tuple(block["summary"])
        lines += [f"## {what}", "", "| side | runs | median (s) | min (s) | median minor faults | peak RSS median / max (GiB) | "
                  "median stages (s) |", "|---|---:|---:|---:|---:|---:|---|"]
        for name in names:
            r = block["summary"][name]
            stages = ", ".join(f"{k} {v:.2f}" for k, v in r.get("median_stages_s", {}).items()) or "-"
            lines.append(f"| {name} | {r['runs']} | {r['median_s']:.2f} | {r['min_s']:.2f} | "
                         f"{_num(r.get('median_faults'), ',.0f')} | {_num(r.get('median_rss_gib'), '.2f')} / "
                         f"{_num(r.get('max_rss_gib'), '.2f')} | {stages} |")
        a, b = (block["summary"][n] for n in names)
        lines += ["", f"Median difference ({names[1]} - {names[0]}): {b['median_s'] - a['median_s']:+.2f} s. "
                      "Runs in order: " + ", ".join(f"{r['side']} {r['seconds']:.2f}" for r in block["runs"]), ""]
        digests = sorted({r["mesh_sha256"] for r in block["runs"] if "mesh_sha256" in r})
        if digests:
            lines += [f"Output meshes: {len(digests)} distinct over {len(block['runs'])} runs (sha256 "
                      f"{', '.join(d[:12] for d in digests)}).", ""]
    return "\n".join(lines)


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    blocks = result["blocks"]
    fig, axes = plt.subplots(1, len(blocks), figsize=(5.5 * len(blocks), 3.8), squeeze=False)
    for ax, (what, block) in zip(axes[0], blocks.items()):
        for name, marker in zip(block["summary"], "os"):
            xs = [i for i, r in enumerate(block["runs"]) if r["side"] == name]
            ax.plot(xs, [block["runs"][i]["seconds"] for i in xs], marker, label=name)
        ax.set(xlabel="run, in the order run", ylabel="seconds", title=what)
        ax.legend()
    fig.suptitle(result["title"])
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def run_block(sides: tuple[Side, Side], pairs: int, one) -> dict:
    runs = []
    for side in alternate(sides, pairs):
        runs.append({"side": side.name, **one(side)})
        print(json.dumps(runs[-1]), flush=True)
    return {"runs": runs, "summary": summary(runs, (sides[0].name, sides[1].name))}


def _revision(rev: str) -> str:
    proc = subprocess.run(["git", "rev-parse", "--verify", f"{rev}^{{commit}}"], cwd=REPO, capture_output=True,
                          text=True)
    if proc.returncode:
        sys.exit(f"completion_ab.py: {rev!r} is not a commit of this repository")
    return proc.stdout.strip()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="mode", required=True)
    a = sub.add_parser("allocator", help="this tree, tuned allocator vs glibc's defaults")
    b = sub.add_parser("base", help="an earlier revision vs this tree")
    b.add_argument("rev")
    for q in (a, b):
        q.add_argument("--pairs", type=int, default=5)
        q.add_argument("--stage", choices=("coarse", "full"), default="coarse")
        scene = q.add_mutually_exclusive_group()
        scene.add_argument("--width", type=float, default=None,
                           help="a 40 x WIDTH m strip (default: the default region)")
        scene.add_argument("--input", default=None, help="run `hgca complete INPUT` (a scan file or a log folder)")
        q.add_argument("--out", default=None, help="result stem in benchmarks/results (default: by mode)")
    args = p.parse_args(argv)
    out_dir = REPO / "benchmarks" / "results"
    name = args.out or ("allocator" if args.mode == "allocator" else f"then_now_{args.stage}")
    if args.input is not None and args.out is None:
        name += f"_{Path(args.input).name.split('.')[0]}"
    check_outputs([out_dir / f"{name}.{e}" for e in ("json", "md", "png")], [])
    here = Side("this tree", REPO)
    with tempfile.TemporaryDirectory(prefix="hgca_base_") as tmp:
        if args.mode == "allocator":
            sides = (Side("tuned", REPO), Side("system", REPO, ((ALLOCATOR_SWITCH, "system"),)))
            title = f"allocator: tuned vs {ALLOCATOR_SWITCH}=system (glibc's defaults)"
        else:
            commit = _revision(args.rev)
            subprocess.run(["git", "worktree", "add", "--detach", f"{tmp}/tree", commit], cwd=REPO, check=True,
                           capture_output=True)
            sides = (Side(f"{commit[:7]}", Path(tmp) / "tree"), here)
            title = f"revision {commit[:7]} (its own code and shipped weights) vs this tree"
        try:
            if args.input is not None:
                path = str(Path(args.input).resolve())
                blocks = {f"hgca complete {Path(path).name} --stage {args.stage}":
                          run_block(sides, args.pairs, lambda s: cli_run(s, args.stage, path))}
            else:
                where = "default region" if args.width is None else f"40 x {args.width:g} m"
                blocks = {f"completion, stage {args.stage}, {where}":
                          run_block(sides, args.pairs, lambda s: completion_run(s, args.stage, args.width))}
        finally:
            if args.mode == "base":
                subprocess.run(["git", "worktree", "remove", "--force", f"{tmp}/tree"], cwd=REPO, capture_output=True)
    result = {"machine": machine(), "title": title, "blocks": blocks}
    (out_dir / f"{name}.json").write_text(json.dumps(result, indent=1))
    (out_dir / f"{name}.md").write_text(table(result))
    plot(result, out_dir / f"{name}.png")
    print(table(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())

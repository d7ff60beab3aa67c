"""How long Blender's main thread stalls while a completion's results go into the scene: one go vs slices.

    .venv/bin/python benchmarks/blender_insert.py [--faces 400000] [--samples 3] [--drive-faces 2000000]
    .venv/bin/python benchmarks/blender_insert.py --page-only     (the page and chart again from the .json)

Builds realistic results synthetically (wavy surfaces of two triangles per grid square, 1 km from the origin, with
observed distances), then inserts each in one process of bpy from .venv:

* one go: `mesh_build.build_results`, everything in one call on the main thread (the whole call is one stall);
* sliced: `result_insert.start_completion` and `step()` called as the job's timer calls it (every
  `completion.INSERT_INTERVAL_S`); every call is timed, and the longest is the stall. The files are read and the
  agreement, colours and edges computed on the worker thread meanwhile.

Cases: a full completion (`--samples` samples of `--faces` triangles, agreement between them) and a drive's merged
mesh (one mesh of `--drive-faces`). Writes benchmarks/results/blender_insert.{json,md,png}.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="hgca_bench_user_"))

import bpy  # noqa: E402
import numpy as np  # noqa: E402

from hgca_blender.jobs import completion  # noqa: E402
from hgca_blender.scene import mesh_build, result_insert  # noqa: E402


def write_result(path: Path, faces: int, seed: int) -> tuple[int, int]:
    """A result file of about `faces` triangles in spatial order (as the core's meshes come), 1 km out."""
    n = int(np.sqrt(faces / 2)) + 1
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.arange(n) * 0.1, np.arange(n) * 0.1)
    z = np.sin(xs / 3.0 + seed) + 0.3 * np.cos(ys / 2.0)
    verts = np.c_[xs.ravel(), ys.ravel(), z.ravel()] + rng.normal(0, 0.01, (n * n, 3))
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel()
    tris = np.stack([np.c_[a, b, d], np.c_[a, d, c]], axis=1).reshape(-1, 3)[:faces].astype(np.int32)
    np.savez(path, vertices=verts.astype(np.float32), faces=tris, offset=np.array([1000.0, 2000.0, 0.0]),
             observed_distance=rng.uniform(0.0, 0.6, n * n).astype(np.float32))
    return n * n, len(tris)


def one_go(paths: list[Path]) -> dict:
    bpy.ops.wm.read_homefile(use_empty=True)
    t0 = time.perf_counter()
    coll = mesh_build.build_results(bpy.context.scene, paths, "hGCA bench")
    took = time.perf_counter() - t0
    assert len(coll.objects) == len(paths)
    return {"max_stall_s": took, "total_s": took, "calls": 1}


def sliced(paths: list[Path]) -> dict:
    bpy.ops.wm.read_homefile(use_empty=True)
    calls = []
    t0 = time.perf_counter()
    insertion = result_insert.start_completion(bpy.context.scene, paths, "hGCA bench")
    calls.append(time.perf_counter() - t0)
    while True:
        time.sleep(completion.INSERT_INTERVAL_S)     # the timer's pause: Blender draws and answers the user here
        began = time.perf_counter()
        more = insertion.step()
        calls.append(time.perf_counter() - began)
        if not more:
            break
    total = time.perf_counter() - t0
    assert insertion.state == "done", insertion.error
    assert len(bpy.data.collections[insertion.result].objects) == len(paths)
    return {"max_stall_s": max(calls), "total_s": total, "calls": len(calls),
            "adding_slices": len(insertion.slices), "longest_step_s": insertion.longest_step,
            "longest_step": insertion.longest_name,
            "timeline": [round(c, 4) for c in calls]}


def chart(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = list(results["cases"])
    fig, (bars, line) = plt.subplots(1, 2, figsize=(9, 2.8), gridspec_kw={"width_ratios": [1, 1.4]})
    y = np.arange(len(cases))
    bars.barh(y + 0.2, [results["cases"][c]["one_go"]["max_stall_s"] for c in cases], 0.4, label="one go")
    bars.barh(y - 0.2, [results["cases"][c]["sliced"]["max_stall_s"] for c in cases], 0.4, label="sliced")
    bars.axvline(1.0, color="k", lw=0.8, ls="--", label="1 s")
    bars.set_yticks(y, [results["cases"][c]["label"] for c in cases], fontsize=7)
    bars.set_xlabel("longest main-thread stall (s)")
    bars.legend(fontsize=7)
    for c in cases:
        stalls = results["cases"][c]["sliced"]["timeline"]
        line.plot(np.arange(len(stalls)), stalls, marker=".", lw=0.8, ms=3, label=results["cases"][c]["label"])
    line.axhline(results["slice_s"], color="k", lw=0.8, ls="--", label="slice budget")
    line.set_xlabel("timer call")
    line.set_ylabel("stall (s)")
    line.set_title("sliced: every call", fontsize=8)
    line.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def write_page(results: dict, out: Path) -> None:
    lines = ["# Results into the scene without freezing Blender", "",
             f"bpy {results['bpy']}, Python {results['python']}, {results['cpus']} CPUs shared with other jobs "
             f"(1-min load average {results['load_avg_start']} at start, {results['load_avg_end']} at end); one run "
             f"of each. Slice budget `SLICE_S` = {results['slice_s']} s, timer pause "
             f"{results['interval_s']} s between calls. Produced by `benchmarks/blender_insert.py`.", "",
             "One go is `mesh_build.build_results` (reading, agreement and meshes in one call on the main thread; "
             "the entry point for scripts). Sliced is `result_insert`: the files are read and the agreement, "
             "colours and edges computed on a worker thread, and the job's timer calls `step()`, which adds "
             "Blender data until its budget is spent. A stall is one call on the main thread; total is from the "
             "job's end to the last object in the scene.", "",
             "![longest stall and every sliced call](blender_insert.png)", "",
             "| result | vertices | triangles | one go: stall = total (s) | sliced: longest stall (s) | "
             "sliced: total (s) | timer calls | longest single step (s) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for case in results["cases"].values():
        one, sl = case["one_go"], case["sliced"]
        lines.append(f"| {case['label']} | {case['vertices']:,} | {case['triangles']:,} | {one['max_stall_s']:.2f} | "
                     f"{sl['max_stall_s']:.3f} | {sl['total_s']:.2f} | {sl['calls']} | {sl['longest_step_s']:.3f} "
                     f"(`{sl['longest_step']}`) |")
    lines += ["", "A slice ends after the step that spends its budget, and a step that its kind's measured rate says "
              "would overrun what is left waits for the next slice; so a call lasts about the budget, or one large "
              "step alone. The longest single step is one copy into one mesh that Blender cannot split (`faces`: "
              "storing each face's first corner, `polygons.foreach_set(\"loop_start\")`, which Blender copies face by "
              "face; `corners`: adding the corners and their vertex and edge indices). It grows with the faces of "
              "one mesh and with the load on the machine.", ""]
    out.with_suffix(".md").write_text("\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--faces", type=int, default=400_000, help="triangles per sample of the completion")
    ap.add_argument("--samples", type=int, default=3)
    ap.add_argument("--drive-faces", type=int, default=2_000_000, help="triangles of the drive's merged mesh")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "blender_insert"))
    ap.add_argument("--page-only", action="store_true", help="rewrite the page and chart from OUT.json")
    args = ap.parse_args(argv)
    if args.page_only:
        results = json.loads(Path(args.out).with_suffix(".json").read_text())
        chart(results, Path(args.out).with_suffix(".png"))
        write_page(results, Path(args.out))
        return 0
    work = Path(tempfile.mkdtemp(prefix="hgca_bench_insert_"))
    results: dict = {"bpy": bpy.app.version_string, "python": platform.python_version(), "cpus": os.cpu_count(),
                     "load_avg_start": round(os.getloadavg()[0], 2), "slice_s": result_insert.SLICE_S,
                     "interval_s": completion.INSERT_INTERVAL_S, "cases": {}}
    cases = {"completion": (f"completion, {args.samples} samples", [args.faces] * args.samples),
             "drive": ("drive merge, 1 mesh", [args.drive_faces])}
    for key, (label, sizes) in cases.items():
        paths, verts, tris = [], 0, 0
        for i, faces in enumerate(sizes):
            paths.append(work / f"{key}_s{i}.npz")
            v, f = write_result(paths[-1], faces, i)
            verts, tris = verts + v, tris + f
        case = {"label": label, "vertices": verts, "triangles": tris}
        case["one_go"] = one_go(paths)
        print(f"{label}: one go {case['one_go']}", flush=True)
        case["sliced"] = sliced(paths)
        print(f"{label}: sliced { {k: v for k, v in case['sliced'].items() if k != 'timeline'} }", flush=True)
        results["cases"][key] = case
    results["load_avg_end"] = round(os.getloadavg()[0], 2)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(results, indent=1))
    chart(results, out.with_suffix(".png"))
    write_page(results, out)
    print(out.with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

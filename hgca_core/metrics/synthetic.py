"""`hgca eval`'s scoring of the synthetic split: each method's completions of one sample, scored against its
ground truth (the paper's Table 1 metrics, `metrics.evaluate`), timed by the method's own work."""
from __future__ import annotations

import time
from pathlib import Path

from hgca_core.config import CompletionConfig


def load_method_models(methods: list[str], fine_weights: str | None, weights: str | None = None,
                       noplanner_weights: str | None = None) -> dict:
    """`pipeline.Models` per model-based method: gca = the no-planner weights, hgca / hgca-full = the planner
    weights (with the fine stage when hgca-full is asked for), shipped unless named, loaded once for the split."""
    from hgca_core.models.weights import weights_files
    from hgca_core.pipeline import load_models

    files = weights_files(methods, weights, fine_weights, noplanner_weights)   # the files `weights_record` names
    models = {}
    if "noplanner" in files:
        models["gca"] = load_models("coarse", files["noplanner"])
    if "coarse" in files:
        models["hgca"] = load_models("full" if "fine" in files else "coarse", files["coarse"], files.get("fine"))
    return models


def evaluate_methods(path: Path, methods: list[str], models: dict, settings: CompletionConfig,
                     keep: dict | None = None) -> dict:
    """{row: (metrics of the k completions of one sample, seconds per completion)} for each method's rows; the
    seconds are the method's own (making the completion and its mesh), not the scoring's. `keep`, when given,
    receives each row's first mesh ({row: trimesh}), the one scored first.

    Model rows run the product's region-frame core (`pipeline.complete_local`) on the sample's input, which the
    dataset stores in its region frame, and score the meshes it returns: the coarse stage's cube-face mesh for
    gca / hgca, the implicit mesh for hgca-implicit; hgca-10cm scores the fine cells, meshed by the same
    `voxel_mesh`, as is the input row. hgca borrows the coarse cells of hgca-full's run when both are asked for
    (the same weights and seeds give the same chains); its time is then that run's coarse share plus meshing.
    """
    import numpy as np

    from hgca_core.dataset.samples import load_sample
    from hgca_core.geometry.region import Region
    from hgca_core.geometry.voxel import COARSE, FINE, downsample
    from hgca_core.meshing.voxel_mesh import voxel_mesh
    from hgca_core.metrics.baselines import input_baseline, poisson_baseline
    from hgca_core.metrics.evaluate import evaluate_sample
    from hgca_core.pipeline import complete_local
    from hgca_core.progress import StageClock
    from hgca_core.synth.rays import input_rays

    sample = load_sample(path)
    pts = np.asarray(sample["input_points"], dtype=np.float64)
    rays, ray_scan = input_rays(sample)   # hgca's free space walks every ray, as on a real scan
    region = Region.from_tuple(sample["region"])
    k = settings.samples
    runs: dict[tuple[str, str], tuple[list, StageClock]] = {}
    coarse_stages = ("voxelise", "planner", "coarse")

    def core(name: str, stage: str) -> tuple[list, StageClock]:
        if (name, stage) not in runs:
            clock = StageClock()
            # every triangle scored (max_faces 0), whatever the config's face limit
            runs[name, stage] = (complete_local(rays, region, models[name], settings.with_(stage=stage, max_faces=0),
                                                progress=clock, origins=sample["input_origins"],
                                                origin_index=ray_scan), clock)
        return runs[name, stage]

    out = {}
    for m in methods:
        t0 = time.perf_counter()
        if m == "input":
            cells, mesh = input_baseline(pts, region.size)
            secs = time.perf_counter() - t0
            out[m] = (evaluate_sample(sample, [mesh], [cells]), secs)
        elif m == "poisson":
            mesh = poisson_baseline(pts, np.asarray(sample["input_origins"]))
            secs = time.perf_counter() - t0
            out[m] = (evaluate_sample(sample, [mesh]), secs)
        elif m == "hgca-full":  # one fine run per completion, scored as 10 cm voxels and as the implicit mesh
            done, clock = core("hgca", "full")
            gen = clock.total(*coarse_stages, "fine")
            vox = [voxel_mesh(r.fine_cells, FINE) for r in done]
            out["hgca-10cm"] = (evaluate_sample(sample, vox, [downsample(r.fine_cells) for r in done]), gen / k)
            out["hgca-implicit"] = (evaluate_sample(sample, [r.mesh for r in done]), (gen + clock.total("mesh")) / k)
        elif m == "hgca" and "hgca-full" in methods:
            done, clock = core("hgca", "full")
            t1 = time.perf_counter()
            meshes = [voxel_mesh(r.coarse_cells, COARSE) for r in done]   # what complete_local's coarse stage ships
            secs = clock.total(*coarse_stages) + time.perf_counter() - t1
            out[m] = (evaluate_sample(sample, meshes, [r.coarse_cells for r in done]), secs / k)
        else:  # gca, hgca: the coarse stage as `hgca complete --stage coarse` runs it
            done, clock = core(m, "coarse")
            out[m] = (evaluate_sample(sample, [r.mesh for r in done], [r.coarse_cells for r in done]),
                      clock.total() / k)
        if keep is None:
            continue
        if m in ("input", "poisson"):
            keep[m] = mesh
        elif m == "hgca-full":
            keep.update({"hgca-10cm": vox[0], "hgca-implicit": done[0].mesh})
        else:   # gca, hgca: the mesh scored above (hgca's voxel mesh of hgca-full's cells when both run)
            keep[m] = meshes[0] if m == "hgca" and "hgca-full" in methods else done[0].mesh
    return out

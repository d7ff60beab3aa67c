"""`hgca eval-real`: the label-free scores on hand-made cells, and the command end to end on a small scene with
small untrained weights (the real numbers come from benchmarks/results/real_scans.md)."""
from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from hgca_testdata import tiny_sample
from hgca_core.metrics.realscan import (cut_scores, free_space_scores, generated_cells, in_grid,
                                        recall_within_one, summarise)

SHAPE = (20, 20, 10)


def test_recall_within_one_cell():
    target = np.array([[5, 5, 5], [10, 10, 5]])
    assert recall_within_one(target, np.array([[6, 6, 6]]), SHAPE) == 0.5   # diagonal neighbour counts
    assert recall_within_one(target, np.array([[7, 5, 5]]), SHAPE) == 0.0   # two cells away does not
    assert recall_within_one(target, np.array([[6, 4, 4], [10, 11, 4]]), SHAPE) == 1.0
    assert np.isnan(recall_within_one(np.zeros((0, 3)), target, SHAPE))


def test_generated_and_free_space_share():
    empty = np.zeros(SHAPE, dtype=bool)
    empty[:, :, 5:] = True
    inp = np.array([[1, 1, 1], [2, 2, 6]])
    cells = np.array([[1, 1, 1], [2, 2, 6], [3, 3, 6], [3, 3, 2], [4, 4, 7], [30, 0, 0]])
    np.testing.assert_array_equal(generated_cells(cells, inp, SHAPE), [[3, 3, 6], [3, 3, 2], [4, 4, 7]])
    s = free_space_scores(cells, inp, empty)
    assert s["generated"] == 3 and s["in_empty"] == 2 and s["empty_share"] == pytest.approx(2 / 3)
    assert np.isnan(free_space_scores(inp, inp, empty)["empty_share"])
    np.testing.assert_array_equal(in_grid(np.array([[0, 0, 5], [0, 0, 4], [-1, 0, 5]]), empty), [1, 0, 0])


def test_cut_scores_count_only_above_the_cut():
    empty = np.zeros(SHAPE, dtype=bool)
    empty[10:, :, :] = True
    cut_inp = np.array([[5, 5, 2]])
    away = np.array([[5, 5, 6], [5, 5, 7]])
    # cell centres: z = (c + 0.25) * 0.2; the cut at 1.0 m keeps cells 5.. above
    cells = np.array([[5, 5, 2], [5, 5, 4], [12, 5, 6], [5, 5, 6]])
    s = cut_scores(cells, cut_inp, away, 1.0, empty)
    assert s["recall"] == 1.0                            # (5,5,6) found, (5,5,7) next to it
    assert s["generated_above"] == 2 and s["above_in_empty"] == 1 and s["above_empty_share"] == 0.5


def test_summarise():
    s = summarise([{"a": 0.2, "b": float("nan")}, {"a": 0.4, "b": float("nan")}, {"a": 0.3, "b": float("nan")}])
    assert s["a"] == pytest.approx({"min": 0.2, "mean": 0.3, "max": 0.4, "spread": 0.2})
    assert np.isnan(s["b"]["mean"])


def _naive_recall(target: np.ndarray, found: np.ndarray) -> float:
    found = {tuple(c) for c in found}
    hit = [any((t[0] + dx, t[1] + dy, t[2] + dz) in found for dx in (-1, 0, 1) for dy in (-1, 0, 1)
               for dz in (-1, 0, 1)) for t in target]
    return float(np.mean(hit))


def test_eval_real_command(tmp_path, small_weights):
    s = tiny_sample(3)
    scan = tmp_path / "street.npz"
    offset = np.array([5000.0, 2000.0, 60.0])  # city-scale coordinates, as AV2 gives
    np.savez(scan, points=s["input_points"].astype(np.float64) + offset, origins=[offset + [3.0, 3.0, 3.0]])
    out = tmp_path / "res" / "real.json"
    out.parent.mkdir()
    cmd = [sys.executable, "-m", "hgca_core.cli", "eval-real", str(scan), "--out", str(out), "--methods",
           "input,gca,hgca", "--samples", "2", "--weights", str(small_weights), "--noplanner-weights",
           str(small_weights), "--t1", "2", "--cuts", "0.6,1.0", "--threads", "1"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    doc = json.loads(out.read_text())
    # the results name the weights each model row ran with, by digest (no fine weights: no hgca-full row)
    digest = hashlib.sha256(Path(small_weights).read_bytes()).hexdigest()
    assert doc["config"]["weights"] == {"coarse": str(small_weights), "noplanner": str(small_weights)}
    assert doc["config"]["weights_sha256"] == {"coarse": digest, "noplanner": digest}
    entry = doc["inputs"]["street"]
    assert set(entry["cases"]) == {"full", "cut_0.6", "cut_1", }
    assert doc["waymo_protocol"]["applicable"] is False
    full = entry["cases"]["full"]["rows"]
    assert set(full) == {"input", "gca", "hgca"} and full["gca"]["k"] == 2 and full["input"]["k"] == 1
    assert full["input"]["per_sample"][0]["generated"] == 0
    assert full["hgca"]["per_sample"][0]["generated"] > 0
    cut = entry["cases"]["cut_0.6"]
    assert cut["cut_away_cells"] > 20
    # the input row's recall, recomputed here from the cells: cut-away cells next to a kept cell
    from hgca_core.geometry.region import Region
    from hgca_core.geometry.voxel import COARSE, voxelize

    region = Region(np.array(entry["region"][:3]), np.array(entry["region"][3:6]))
    local = region.to_local(s["input_points"].astype(np.float64) + offset)
    low = local[:, 2] < 1.6
    kept, away = voxelize(local[low], COARSE), voxelize(local[~low], COARSE)
    away = away[~(away[:, None] == kept[None]).all(-1).any(1)]
    assert len(away) == cut["cut_away_cells"]
    assert cut["rows"]["input"]["per_sample"][0]["recall"] == pytest.approx(_naive_recall(away, kept))
    md = out.with_suffix(".md").read_text()
    assert "| street | 0.6 m | GCA (no planner) | 2 |" in md and "Waymo" in md
    for png in ("real_street.png", "real_street_cut1.png"):
        image = np.asarray(Image.open(out.parent / png))
        assert (image < 250).any(axis=-1).mean() > 0.01  # something was drawn


def _red_pixels(path: Path) -> int:
    im = np.asarray(Image.open(path)).astype(int)
    return int(((im[..., 0] > 200) & (im[..., 1] < 60) & (im[..., 2] < 60)).sum())


def test_marked_points_show_on_a_surface_not_behind_it(tmp_path):
    import trimesh

    from hgca_core.render import render_mesh

    plane = trimesh.Trimesh([[0, 0, 0], [4, 0, 0], [4, 4, 0], [0, 4, 0]], [[0, 1, 2], [0, 2, 3]])
    grid = np.stack(np.meshgrid(np.linspace(1, 3, 40), np.linspace(1, 3, 40)), -1).reshape(-1, 2)
    eye, target = np.array([2.0, -3.0, 6.0]), np.array([2.0, 2.0, 0.0])
    for z, name in ((0.0, "on.png"), (-1.0, "behind.png")):
        render_mesh(plane, tmp_path / name, marked=np.c_[grid, np.full(len(grid), z)], eye=eye, target=target,
                    size=(300, 200))
    assert _red_pixels(tmp_path / "on.png") > 200
    assert _red_pixels(tmp_path / "behind.png") == 0


def test_eval_real_missing_input(tmp_path):
    res = subprocess.run([sys.executable, "-m", "hgca_core.cli", "eval-real", str(tmp_path / "none.ply"),
                          "--out", str(tmp_path / "r.json"), "--methods", "input"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 2 and "file not found" in res.stderr and not (tmp_path / "r.json").exists()


def test_resume_keeps_cases_only_in_the_same_region(tmp_path):
    s = tiny_sample(4)
    scan = tmp_path / "street.npz"
    np.savez(scan, points=s["input_points"].astype(np.float64), origins=[[3.0, 3.0, 3.0]])
    out = tmp_path / "r.json"
    base = [sys.executable, "-m", "hgca_core.cli", "eval-real", str(scan), "--out", str(out), "--methods", "input",
            "--samples", "1", "--no-render"]
    run = lambda *extra: subprocess.run(base + list(extra), capture_output=True, text=True, timeout=300)  # noqa: E731
    assert run("--cuts", "1.0").returncode == 0
    doc = json.loads(out.read_text())
    doc["inputs"]["street"]["cases"]["cut_1"]["points"] = -1  # a marker: kept cases keep it
    out.write_text(json.dumps(doc))
    res = run("--cuts", "1.0,0.5", "--resume")
    assert res.returncode == 0, res.stderr
    cases = json.loads(out.read_text())["inputs"]["street"]["cases"]
    assert cases["cut_1"]["points"] == -1 and cases["cut_0.5"]["points"] > 0
    doc = json.loads(out.read_text())
    doc["inputs"]["street"]["region"][2] += 0.1  # as if older code had placed the box elsewhere
    out.write_text(json.dumps(doc))
    res = run("--cuts", "1.0,0.5", "--resume")
    assert res.returncode == 0 and "region differs" in res.stderr
    assert json.loads(out.read_text())["inputs"]["street"]["cases"]["cut_1"]["points"] > 0
    # other sampling settings cannot be resumed
    res = run("--cuts", "1.0", "--resume", "--seed", "1")
    assert res.returncode == 2 and "other settings" in res.stderr


def test_yaw_turns_the_scored_region_about_the_sensor(tmp_path):
    s = tiny_sample(4)
    scan = tmp_path / "street.npz"
    np.savez(scan, points=s["input_points"].astype(np.float64), origins=[[3.0, 3.0, 3.0]])
    base = [sys.executable, "-m", "hgca_core.cli", "eval-real", str(scan), "--methods", "input", "--samples", "1",
            "--cuts", "1.0", "--no-render"]
    docs = {}
    for yaw in ("0", "30"):
        out = tmp_path / f"r{yaw}.json"
        res = subprocess.run(base + ["--out", str(out), "--yaw", yaw], capture_output=True, text=True, timeout=300)
        assert res.returncode == 0, res.stderr[-2000:]
        docs[yaw] = json.loads(out.read_text())
    plain, turned = (docs[y]["inputs"]["street"]["region"] for y in ("0", "30"))
    assert plain[6] == pytest.approx(0.0) and turned[6] == pytest.approx(30.0)
    assert plain[:6] == pytest.approx(turned[:6])   # same box, centred on the sensor, only turned
    assert docs["30"]["config"]["yaw_deg"] == 30.0
    res = subprocess.run(base + ["--out", str(tmp_path / "bad.json"), "--yaw", "nan"], capture_output=True,
                         text=True, timeout=300)
    assert res.returncode == 2 and "--yaw" in res.stderr and not (tmp_path / "bad.json").exists()


def test_eval_real_free_space_mask_reaches_the_model_rows(tmp_path, small_weights):
    """`--free-space mask` goes to every completion: no generated cell lies in the core of the space the input
    rays passed (fewer in its rim than unmasked), and the setting is recorded (a run with another setting is not
    resumed from it)."""
    s = tiny_sample(3)
    scan = tmp_path / "street.npz"
    np.savez(scan, points=s["input_points"].astype(np.float64), origins=[[3.0, 3.0, 3.0]])
    out = tmp_path / "real.json"
    cmd = [sys.executable, "-m", "hgca_core.cli", "eval-real", str(scan), "--out", str(out), "--methods", "hgca",
           "--samples", "1", "--weights", str(small_weights), "--t1", "2", "--cuts", "1.0", "--threads", "1",
           "--no-render"]
    runs = {}
    for mode in ("off", "mask"):
        res = subprocess.run(cmd + ["--free-space", mode], capture_output=True, text=True, timeout=600)
        assert res.returncode == 0, res.stderr[-3000:]
        doc = json.loads(out.read_text())
        assert doc["config"]["free_space"] == mode
        runs[mode] = doc["inputs"]["street"]["cases"]["full"]["rows"]["hgca"]["per_sample"][0]
    assert runs["off"]["core_share"] > 0         # unmasked, this model grows deep into seen-empty space
    assert runs["mask"]["core_share"] == 0 and runs["mask"]["generated"] > 0
    assert runs["mask"]["in_empty"] < runs["off"]["in_empty"]
    assert "free space mask" in out.with_suffix(".md").read_text()


def test_eval_real_completes_with_each_points_own_sensor_origin(tmp_path, small_weights, monkeypatch):
    """The completions see each point's ray from its own sensor (the reader's origin_index), as `hgca complete`
    does, not the nearest origin: here every point belongs to the farther of two sensors."""
    import hgca_core.pipeline
    from hgca_core.cli import main

    s = tiny_sample(3)
    pts = s["input_points"].astype(np.float64)
    scan = tmp_path / "street.npz"
    np.savez(scan, points=pts, origins=[[3.0, 3.0, 3.0], [3.0, 3.0, 40.0]],
             origin_index=np.ones(len(pts), dtype=np.int64))
    seen = []
    real = hgca_core.pipeline.complete         # what `hgca_core.complete` is, and what eval-real calls

    def spy(points, **kw):
        seen.append((len(points), kw.get("origin_index")))
        return real(points, **kw)

    monkeypatch.setattr(hgca_core.pipeline, "complete", spy)
    out = tmp_path / "real.json"
    assert main(["eval-real", str(scan), "--out", str(out), "--methods", "hgca", "--samples", "1", "--weights",
                 str(small_weights), "--t1", "2", "--cuts", "1.0", "--threads", "1", "--no-render"]) == 0
    assert len(seen) == 2                                        # the whole input and the cut
    assert seen[0][0] == len(pts) and seen[1][0] < len(pts)
    for n, index in seen:
        assert index is not None and len(index) == n and (index == 1).all()


def test_eval_real_runs_the_weights_its_results_name(tmp_path, small_weights, monkeypatch):
    """Each completion loads the file the results' config names for its row (one decision, `weights_files`): the
    given no-planner weights for GCA, the shipped coarse file for hGCA when none is given (by its path, so the
    record's digest is of the file that ran)."""
    import hgca_core.pipeline
    from hgca_core.cli import main
    from hgca_core.models.weights import shipped

    s = tiny_sample(3)
    scan = tmp_path / "street.npz"
    np.savez(scan, points=s["input_points"].astype(np.float64), origins=[[3.0, 3.0, 3.0]])
    seen = []
    real = hgca_core.pipeline.complete         # what `hgca_core.complete` is, and what eval-real calls

    def spy(points, **kw):
        seen.append(str(kw["config"].weights))      # eval-real hands the library one config per row
        return real(points, **kw)

    monkeypatch.setattr(hgca_core.pipeline, "complete", spy)
    out = tmp_path / "real.json"
    assert main(["eval-real", str(scan), "--out", str(out), "--methods", "gca,hgca", "--samples", "1",
                 "--noplanner-weights", str(small_weights), "--t1", "1", "--cuts", "1.0", "--threads", "1", "--no-render"]) == 0
    named = json.loads(out.read_text())["config"]["weights"]
    assert named == {"coarse": str(shipped("coarse")), "noplanner": str(small_weights)}
    assert sorted(seen) == sorted([named["noplanner"], named["coarse"]] * 2)  # two cases, one call a row each

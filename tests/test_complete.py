"""`hgca complete` end to end on a small scene with small (untrained) weights: files, progress protocol,
determinism and errors. Quality is the eval's business; here the plumbing must be exact."""
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from hgca_testdata import tiny_sample
from hgca_core.models.checkpoint import save_weights
from hgca_core.models.gca import GCAConfig, GCAKernel


@pytest.fixture(scope="module")
def small_weights(tmp_path_factory):
    torch.manual_seed(0)
    cfg = GCAConfig(channels=(8, 8, 16, 16, 16), steps=3)
    path = tmp_path_factory.mktemp("w") / "coarse_small.pt"
    save_weights(GCAKernel(cfg), cfg.to_dict(), path, {"kind": "coarse", "stage": "test"})
    return path


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    s = tiny_sample(3)
    path = tmp_path_factory.mktemp("scan") / "scan.npz"
    world = s["input_points"].astype(np.float64) + np.array([100.0, 200.0, -1.0])
    np.savez(path, points=world, origins=np.array([[103.0, 203.0, 2.0]]))
    return path


def _run(*args):
    return subprocess.run([sys.executable, "-m", "hgca_core.cli", "complete", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


REGION = "103,203,1,6,6,4"


def test_jsonl_progress_outputs_and_determinism(small_weights, scan, tmp_path):
    out = tmp_path / "out.npz"
    res = _run(scan, "-o", out, "--weights", small_weights, "--samples", 2, "--seed", 5, "--region", REGION,
               "--progress", "jsonl")
    assert res.returncode == 0, res.stderr
    lines = [json.loads(line) for line in res.stdout.splitlines()]
    stages = [x["stage"] for x in lines]
    assert stages[0] == "read" and stages[-1] == "done" and "coarse" in stages and "write" in stages
    assert all({"step", "total", "message"} <= set(x) for x in lines[:-1])
    outputs = lines[-1]["outputs"]
    assert [p.rsplit("/", 1)[-1] for p in outputs] == ["out_s0.npz", "out_s1.npz"]
    a = np.load(tmp_path / "out_s0.npz")
    assert a["faces"].shape[1] == 3 and len(a["vertices"]) == len(a["observed_distance"])
    # vertices are back in the world frame, inside the region box (+ half a cell)
    assert np.all(a["vertices"][:, 0] > 99.9) and np.all(a["vertices"][:, 0] < 106.1)
    again = tmp_path / "again.npz"
    assert _run(scan, "-o", again, "--weights", small_weights, "--samples", 1, "--seed", 5, "--region", REGION,
                "--progress", "none").returncode == 0
    b = np.load(tmp_path / "again_s0.npz")
    assert np.array_equal(a["vertices"], b["vertices"]) and np.array_equal(a["faces"], b["faces"])


def test_ply_output_has_observed_distance(small_weights, scan, tmp_path):
    from plyfile import PlyData

    res = _run(scan, "-o", tmp_path / "m.ply", "--weights", small_weights, "--region", REGION, "--progress", "none")
    assert res.returncode == 0, res.stderr
    v = PlyData.read(str(tmp_path / "m_s0.ply"))["vertex"]
    d = np.asarray(v["observed_distance"])
    assert len(d) > 0 and np.all(d >= 0)


@pytest.mark.parametrize("args, message", [
    (["--region", "0,0,0,5,5,5"], "no input points inside the region"),
    (["--region", "1,2"], "6 or 7 numbers"),
    (["--region", "103,203,1,100000,100000,4"], "GiB"),
])
def test_bad_input_is_one_clear_error(small_weights, scan, tmp_path, args, message):
    res = _run(scan, "-o", tmp_path / "x.ply", "--weights", small_weights, "--progress", "jsonl", *args)
    assert res.returncode == 2
    assert message in res.stderr and "Traceback" not in res.stderr
    assert json.loads(res.stdout.splitlines()[-1])["stage"] == "error"
    assert not list(tmp_path.glob("x_s*"))


def test_bad_output_and_nan_input(small_weights, scan, tmp_path):
    res = _run(scan, "-o", tmp_path / "x.txt", "--weights", small_weights)
    assert res.returncode == 2 and "output must end in" in res.stderr
    bad = tmp_path / "nan.npz"
    np.savez(bad, points=np.full((10, 3), np.nan))
    res = _run(bad, "-o", tmp_path / "y.ply", "--weights", small_weights)
    assert res.returncode == 2 and "nan.npz" in res.stderr


def test_full_stage_runs_the_fine_path(small_weights, scan, tmp_path):
    """With fine weights (untrained, small), --stage full upsamples at 10 cm and meshes the decoded distance."""
    from hgca_core.models.autoencoder import Autoencoder, AutoencoderConfig
    from hgca_core.models.cgca import CGCAConfig, CGCAKernel, save_fine

    torch.manual_seed(0)
    fine = tmp_path / "fine_small.pt"
    save_fine(CGCAKernel(CGCAConfig(channels=(8, 8, 8, 8, 8), steps=2)), Autoencoder(AutoencoderConfig()), str(fine),
              {"stage": "test"})
    out = tmp_path / "full.npz"
    res = _run(scan, "-o", out, "--weights", small_weights, "--fine-weights", fine, "--stage", "full",
               "--region", REGION, "--progress", "jsonl")
    assert res.returncode == 0, res.stderr[-2000:]
    stages = {json.loads(line)["stage"] for line in res.stdout.splitlines()}
    assert {"coarse", "fine", "mesh", "done"} <= stages
    a = np.load(tmp_path / "full_s0.npz")
    assert len(a["vertices"]) == len(a["observed_distance"]) == len(a["normals"])
    assert len(a["face_material"]) == len(a["faces"])
    if len(a["vertices"]):
        assert np.all(a["vertices"][:, 0] > 99.5) and np.all(a["vertices"][:, 0] < 106.5)
    missing = _run(scan, "-o", tmp_path / "m.ply", "--weights", small_weights, "--fine-weights", tmp_path / "nope.pt",
                   "--stage", "full", "--region", REGION)
    assert missing.returncode == 2 and "nope.pt" in missing.stderr


def test_python_api_returns_arrays_and_is_seeded(small_weights, scan):
    import subprocess as sp

    import hgca_core

    # `import hgca_core` stays light: the API loads torch only when first used
    light = sp.run([sys.executable, "-c", "import sys, hgca_core; print('torch' in sys.modules)"],
                   capture_output=True, text=True)
    assert light.stdout.strip() == "False"
    pts = np.load(scan)["points"]
    region = hgca_core.Region.parse(REGION)
    a = hgca_core.complete(pts, region=region, samples=2, seed=5, weights=small_weights)
    b = hgca_core.complete(pts, region=region, samples=2, seed=5, weights=small_weights)
    assert [r.seed for r in a] == [5, 6]
    for r, s in zip(a, b):
        assert r.vertices.shape[1] == 3 and r.faces.shape[1] == 3 and len(r.observed_distance) == len(r.vertices)
        np.testing.assert_array_equal(r.vertices, s.vertices)
        np.testing.assert_array_equal(r.faces, s.faces)
    # every vertex lies in the region (world frame), and the observed distance is a real distance
    lo, hi = region.center - region.size / 2 - 0.1, region.center + region.size / 2 + 0.1
    assert np.all((a[0].vertices >= lo) & (a[0].vertices <= hi))
    assert np.all(a[0].observed_distance >= 0)
    with pytest.raises(hgca_core.InputError, match="NaN"):
        hgca_core.complete(np.full((10, 3), np.nan), region=region, weights=small_weights)


def test_max_faces_simplifies_each_mesh(small_weights, scan, tmp_path):
    full = _run(scan, "-o", tmp_path / "a.npz", "--weights", small_weights, "--region", REGION, "--progress", "none")
    assert full.returncode == 0, full.stderr[-2000:]
    n = len(np.load(tmp_path / "a_s0.npz")["faces"])
    assert n > 2000
    res = _run(scan, "-o", tmp_path / "b.npz", "--weights", small_weights, "--region", REGION, "--progress", "none",
               "--max-faces", "1000")
    assert res.returncode == 0, res.stderr[-2000:]
    b = np.load(tmp_path / "b_s0.npz")
    assert 500 < len(b["faces"]) <= 1000 and len(b["observed_distance"]) == len(b["vertices"])
    bad = _run(scan, "-o", tmp_path / "c.npz", "--weights", small_weights, "--region", REGION, "--max-faces", "10")
    assert bad.returncode == 2 and "max_faces" in bad.stderr
    every = _run(scan, "-o", tmp_path / "d.npz", "--weights", small_weights, "--region", REGION, "--progress", "none",
                 "--max-faces", "0")                          # 0: keep every triangle
    assert every.returncode == 0, every.stderr[-2000:]
    d = np.load(tmp_path / "d_s0.npz")
    assert len(d["faces"]) == n and len(d["normals"]) == len(d["vertices"])
    np.testing.assert_allclose(np.linalg.norm(d["normals"], axis=1), 1.0, atol=1e-5)


def test_region_too_large_for_memory_is_refused_before_any_work(small_weights, scan):
    import hgca_core

    pts = np.load(scan)["points"]
    with pytest.raises(hgca_core.InputError, match=r"needs about [0-9.]+ GiB.*split it into tiles"):
        hgca_core.complete(pts, region=hgca_core.Region.parse("103,203,1,2000,2000,8"), weights=small_weights)
    res = _run(scan, "-o", "/tmp/never.ply", "--weights", small_weights, "--region", "103,203,1,2000,2000,8")
    assert res.returncode == 2 and "GiB" in res.stderr and "Traceback" not in res.stderr

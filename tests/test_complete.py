"""`hgca complete` end to end on a small scene with small (untrained) weights: files, progress protocol,
determinism and errors. Quality is the eval's business; here the plumbing must be exact."""
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from hgca_testdata import tiny_scan_file
from hgca_core.training.export import save_weights
from hgca_core.progress import PROTOCOL


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    return tiny_scan_file(tmp_path_factory.mktemp("scan"))


def _run(*args):
    return subprocess.run([sys.executable, "-m", "hgca_core.cli", "complete", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


REGION = "103,203,1,6,6,4"


def test_jsonl_progress_outputs_and_determinism(small_weights, scan, tmp_path):
    out = tmp_path / "out.npz"
    res = _run(scan, "-o", out, "--weights", small_weights, "--samples", 2, "--seed", 5, "--region", REGION,
               "--stage", "coarse", "--progress", "jsonl")
    assert res.returncode == 0, res.stderr
    lines = [json.loads(line) for line in res.stdout.splitlines()]
    stages = [x["stage"] for x in lines]
    assert stages[0] == "read" and stages[-1] == "done" and "coarse" in stages and "write" in stages
    assert all({"step", "total", "message"} <= set(x) for x in lines[:-1])
    # every record names the protocol and the sample it is about (docs/CONTRACTS.md, "Progress records")
    assert all(x["protocol"] == PROTOCOL and x["samples"] == 2 for x in lines)
    per_sample = [(x["sample"], x["stage"], x["step"]) for x in lines if x["stage"] in ("coarse", "mesh")]
    assert [s for s, _, _ in per_sample] == sorted(s for s, _, _ in per_sample), "samples come in order"
    for i in (0, 1):
        coarse = [step for s, stage, step in per_sample if s == i and stage == "coarse"]
        assert coarse == list(range(1, 4)), f"sample {i} runs its own T1 = 3 coarse steps"
        assert [step for s, stage, step in per_sample if s == i and stage == "mesh"] == [0, 1]
    assert [x["sample"] for x in lines if x["stage"] == "write"] == [0, 1, 1]
    outputs = lines[-1]["outputs"]
    assert [p.rsplit("/", 1)[-1] for p in outputs] == ["out_s0.npz", "out_s1.npz"]
    a = np.load(tmp_path / "out_s0.npz")
    assert a["faces"].shape[1] == 3 and len(a["vertices"]) == len(a["observed_distance"])
    # vertices are back in the world frame, inside the region box (+ half a cell)
    assert np.all(a["vertices"][:, 0] > 99.9) and np.all(a["vertices"][:, 0] < 106.1)
    again = tmp_path / "again.npz"
    assert _run(scan, "-o", again, "--weights", small_weights, "--samples", 1, "--seed", 5, "--region", REGION,
                "--stage", "coarse", "--progress", "none").returncode == 0
    b = np.load(tmp_path / "again_s0.npz")
    assert np.array_equal(a["vertices"], b["vertices"]) and np.array_equal(a["faces"], b["faces"])


def test_ply_output_has_observed_distance(small_weights, scan, tmp_path):
    from plyfile import PlyData

    res = _run(scan, "-o", tmp_path / "m.ply", "--weights", small_weights, "--region", REGION, "--stage", "coarse",
               "--progress", "none")
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
    from hgca_core.models.cgca import CGCAConfig, CGCAKernel

    torch.manual_seed(0)
    fine = tmp_path / "fine_small.pt"
    save_weights(fine, CGCAKernel(CGCAConfig(channels=(8, 8, 8, 8, 8), steps=2)), {"stage": "test"},
                 autoencoder=Autoencoder(AutoencoderConfig()))
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
    a = hgca_core.complete(pts, region=region, samples=2, seed=5, weights=small_weights, stage="coarse")
    b = hgca_core.complete(pts, region=region, samples=2, seed=5, weights=small_weights, stage="coarse")
    assert [r.seed for r in a] == [5, 6]
    for r, s in zip(a, b):
        assert r.vertices.shape[1] == 3 and r.faces.shape[1] == 3 and len(r.observed_distance) == len(r.vertices)
        np.testing.assert_array_equal(r.vertices, s.vertices)
        np.testing.assert_array_equal(r.faces, s.faces)
    # every vertex lies in the region (world frame), and the observed distance is a real distance
    lo, hi = region.center - region.size / 2 - 0.1, region.center + region.size / 2 + 0.1
    assert np.all((a[0].vertices >= lo) & (a[0].vertices <= hi))
    # ... each vertex's distance to the nearest input point in the region (naive all-pairs reference)
    ins = pts[region.contains_local(region.to_local(pts))]
    pick = np.random.default_rng(0).choice(len(a[0].vertices), size=min(300, len(a[0].vertices)), replace=False)
    naive = np.sqrt(((a[0].vertices[pick, None, :] - ins[None]) ** 2).sum(-1)).min(1)
    np.testing.assert_allclose(a[0].observed_distance[pick], naive, atol=1e-5)
    assert naive.max() > 0.05            # not all at the points: the check can fail
    with pytest.raises(hgca_core.InputError, match="NaN"):
        hgca_core.complete(np.full((10, 3), np.nan), region=region, weights=small_weights)


def test_max_faces_simplifies_each_mesh(small_weights, scan, tmp_path):
    full = _run(scan, "-o", tmp_path / "a.npz", "--weights", small_weights, "--region", REGION, "--stage", "coarse",
                "--progress", "none")
    assert full.returncode == 0, full.stderr[-2000:]
    n = len(np.load(tmp_path / "a_s0.npz")["faces"])
    assert n > 2000
    res = _run(scan, "-o", tmp_path / "b.npz", "--weights", small_weights, "--region", REGION, "--progress", "none",
               "--stage", "coarse", "--max-faces", "1000")
    assert res.returncode == 0, res.stderr[-2000:]
    b = np.load(tmp_path / "b_s0.npz")
    assert 500 < len(b["faces"]) <= 1000 and len(b["observed_distance"]) == len(b["vertices"])
    bad = _run(scan, "-o", tmp_path / "c.npz", "--weights", small_weights, "--region", REGION, "--stage", "coarse",
               "--max-faces", "10")
    assert bad.returncode == 2 and "argument --max-faces: must be 0 (keep every triangle) or at least" in bad.stderr
    every = _run(scan, "-o", tmp_path / "d.npz", "--weights", small_weights, "--region", REGION, "--progress", "none",
                 "--stage", "coarse", "--max-faces", "0")     # 0: keep every triangle
    assert every.returncode == 0, every.stderr[-2000:]
    d = np.load(tmp_path / "d_s0.npz")
    assert len(d["faces"]) == n and len(d["normals"]) == len(d["vertices"])
    np.testing.assert_allclose(np.linalg.norm(d["normals"], axis=1), 1.0, atol=1e-5)


def test_region_too_large_for_memory_is_refused_before_any_work(small_weights, scan):
    import hgca_core

    pts = np.load(scan)["points"]
    with pytest.raises(hgca_core.InputError, match=r"needs about [0-9.,]+ GiB.*split it into tiles"):
        hgca_core.complete(pts, region=hgca_core.Region.parse("103,203,1,2000,2000,8"), weights=small_weights)
    res = _run(scan, "-o", "/tmp/never.ply", "--weights", small_weights, "--region", "103,203,1,2000,2000,8")
    assert res.returncode == 2 and "GiB" in res.stderr and "Traceback" not in res.stderr


class Payload:
    """A weights file's content whose unpickling would run `touch MARKER`."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        import os

        return os.system, (f"touch {self.marker}",)


@pytest.mark.parametrize("flag", ["--weights", "--fine-weights"])
def test_weights_that_would_run_code_neither_run_nor_crash(small_weights, scan, tmp_path, flag):
    marker = tmp_path / "payload_ran"
    evil = tmp_path / "evil.pt"
    torch.save({"kind": "coarse", "config": Payload(marker), "state_dict": {}, "meta": {}}, evil)
    weights = ["--weights", evil] if flag == "--weights" else ["--weights", small_weights, "--fine-weights", evil,
                                                               "--stage", "full"]
    res = _run(scan, "-o", tmp_path / "x.ply", *weights, "--region", REGION, "--progress", "none")
    assert res.returncode == 2 and not marker.exists()
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"hgca complete: error: {evil}: refused: it holds pickled"), lines
    assert not list(tmp_path.glob("x_s*"))


def test_weights_for_another_flag_say_what_they_are_before_any_work(small_weights, tmp_path, capsys):
    """The scan does not exist: an error about the weights shows they were checked before anything was read."""
    from hgca_core.cli import main
    from hgca_core.models.autoencoder import Autoencoder, AutoencoderConfig
    from hgca_core.models.cgca import CGCAConfig, CGCAKernel
    from hgca_core.models.weights import load_file, save_file

    ae = save_weights(tmp_path / "autoencoder.pt", Autoencoder(AutoencoderConfig()))
    fine = save_weights(tmp_path / "fine.pt", CGCAKernel(CGCAConfig(channels=(8, 8, 8, 8, 8), steps=2)),
                        autoencoder=Autoencoder(AutoencoderConfig()))
    empty = save_file({**load_file(small_weights), "config": {}}, tmp_path / "empty_config.pt")
    cases = [(["--weights", fine], "fine.pt: this file holds fine-stage weights (cGCA kernel with its autoencoder), "
                                   "which `hgca complete --fine-weights` takes; `hgca complete --weights` takes "
                                   "coarse-stage weights"),
             (["--weights", ae], "autoencoder.pt: this file holds autoencoder weights"),
             (["--weights", empty], "empty_config.pt: the config is empty"),
             (["--weights", small_weights, "--stage", "full", "--fine-weights", small_weights],
              "coarse_small.pt: this file holds coarse-stage weights (GCA kernel), which `hgca complete --weights` "
              "takes; `hgca complete --fine-weights` takes fine-stage weights")]
    for args, message in cases:
        code = main(["complete", str(tmp_path / "missing_scan.las"), "-o", str(tmp_path / "x.ply"),
                     "--progress", "none", *map(str, args)])
        err = capsys.readouterr().err.strip()
        assert code == 2 and len(err.splitlines()) == 1 and message in err, err
        assert "missing_scan" not in err and "Traceback" not in err


def test_world_wrapper_is_the_region_core_moved_to_the_world(small_weights, scan):
    """`complete` = crop + `complete_local` in the region frame + the mesh moved back; points outside the box are
    dropped by the core itself, so a caller that passes uncropped region-frame points gets the same result."""
    import hgca_core
    from hgca_core.pipeline import complete_local, load_models

    pts = np.load(scan)["points"]
    region = hgca_core.Region.parse(REGION + ",30")               # a turned box: the frames really differ
    world = hgca_core.complete(pts, region=region, samples=2, seed=7, weights=small_weights, precision="fp32",
                               stage="coarse")
    local = complete_local(region.to_local(pts), region, load_models("coarse", small_weights), stage="coarse",
                           samples=2, seed=7, precision="fp32")
    assert len(world) == len(local) == 2
    for w, c in zip(world, local):
        assert w.seed == c.seed and np.array_equal(w.coarse_cells, c.coarse_cells) and len(c.coarse_cells) > 0
        assert np.array_equal(w.faces, c.mesh.faces)
        np.testing.assert_allclose(w.vertices, region.to_world(c.mesh.vertices), rtol=0, atol=1e-9)
    assert not np.array_equal(local[0].coarse_cells, local[1].coarse_cells)
    with pytest.raises(hgca_core.InputError, match="inside"):
        complete_local(region.to_local(pts) + 1000.0, region, load_models("coarse", small_weights), stage="coarse")


def test_stage_defaults_to_full(small_weights, scan, tmp_path):
    """Without --stage the CLI runs the fine stage too (like `make demo` and the Blender panel): so it asks for
    fine weights, and a missing fine file is the error, before any sampling."""
    res = _run(scan, "-o", tmp_path / "x.npz", "--weights", small_weights, "--fine-weights", tmp_path / "nope.pt",
               "--region", REGION, "--progress", "jsonl")
    assert res.returncode == 2 and "nope.pt" in res.stderr and "Traceback" not in res.stderr
    assert "coarse" not in {json.loads(line)["stage"] for line in res.stdout.splitlines()}


def _region_json(*args):
    res = subprocess.run([sys.executable, "-m", "hgca_core.cli", "region", *map(str, args), "--json"],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout)


def test_region_command_prints_the_region_complete_uses(small_weights, scan, tmp_path):
    """`hgca region` (what the add-on's Add Region Box asks) and `hgca complete` without --region pick one box."""
    import hgca_core

    got = _region_json(scan)
    data = np.load(scan)
    (res,) = hgca_core.complete(data["points"], origins=data["origins"], stage="coarse", t1=1, weights=small_weights)
    np.testing.assert_allclose(got["region"], res.region.as_tuple(), rtol=0, atol=1e-9)
    assert got["region_arg"] == ",".join(repr(v) for v in got["region"])
    assert hgca_core.Region.parse(got["region_arg"]).as_tuple() == tuple(got["region"])
    # centred on the sensor, not on the points; the bottom 1 m under the ground the box was placed on
    assert got["centred_on"] == "sensor" and got["center"][:2] == [103.0, 203.0]
    assert got["size"] == [38.4, 38.4, 8.0] and got["yaw_deg"] == 0.0
    assert got["ground_z"] == pytest.approx(got["center"][2] - 4.0 + 1.0)
    assert got["ground_z"] == pytest.approx(0.0, abs=0.05)  # tiny_sample's ground is z = 1, the scan moved 1 m down

    # no sensor known: the points' x/y median, the same in both
    bare = tmp_path / "bare.npz"
    np.savez(bare, points=data["points"])
    got = _region_json(bare, "--size", "20,10,6")
    expect = hgca_core.Region.around(data["points"], size=(20.0, 10.0, 6.0))
    assert got["centred_on"] == "median" and got["size"] == [20.0, 10.0, 6.0]
    np.testing.assert_allclose(got["region"], expect.as_tuple(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(got["center"][:2], np.median(data["points"][:, :2], axis=0), atol=1e-9)


@pytest.mark.parametrize("args, message", [
    (["--size", "1,2"], "three positive numbers"),
    (["--size", "1,-2,3"], "three positive numbers"),
    (["--poses", "/nonexistent/poses.json"], "poses.json"),
])
def test_region_command_bad_input(scan, args, message):
    res = subprocess.run([sys.executable, "-m", "hgca_core.cli", "region", str(scan), *args, "--json"],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and message in res.stderr and "Traceback" not in res.stderr and res.stdout == ""


def test_addon_reads_the_protocol_the_core_writes():
    """hgca_blender.core (bpy-free) stops a job whose records carry another protocol: the two numbers must move together."""
    from hgca_blender.jobs.core import PROGRESS_PROTOCOL

    assert PROGRESS_PROTOCOL == PROTOCOL

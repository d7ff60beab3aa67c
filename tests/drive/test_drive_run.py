"""`hgca drive` end to end on a small synthetic drive (12.8 m tiles, small untrained weights, coarse stage):
every tile exactly once, one merged mesh per sample without doubled overlap, resume after a kill, re-runs that
keep or recompute exactly what their key says, georeferenced drives, and bad input."""
import json
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData
from scipy.spatial import cKDTree

import hgca_core
from drive_data import write_drive

SMALL = {"size": 12.8, "overlap": 3.2, "stage": "coarse", "t1": 3, "threads": 1}
CLI_SMALL = ["--size", "12.8", "--overlap", "3.2", "--stage", "coarse", "--t1", "3", "--threads", "1"]


def read_ply(path):
    ply = PlyData.read(str(path))
    v = ply["vertex"]
    xyz = np.c_[v["x"], v["y"], v["z"]].astype(np.float64)
    faces = np.vstack(ply["face"]["vertex_indices"]) if ply["face"].count else np.zeros((0, 3), int)
    return xyz, faces, np.asarray(v["observed_distance"])


def doubled_faces(xyz, faces, tol=0.01):
    """Faces whose centroid has another face's centroid within `tol` (a voxel mesh's own faces are >= 4 cm apart)."""
    c = xyz[faces].mean(axis=1)
    pairs = cKDTree(c).query_pairs(tol)
    return len(pairs)


@pytest.fixture(scope="module")
def flat_drive(tmp_path_factory):
    """Straight and flat: consecutive tiles' grids coincide, so uncut overlaps would repeat faces exactly."""
    return write_drive(tmp_path_factory.mktemp("flat"), length=40.0, weave=0.0)


@pytest.fixture(scope="module")
def finished(flat_drive, drive_weights, tmp_path_factory):
    out = tmp_path_factory.mktemp("out") / "drive"
    scans, poses = flat_drive
    doc = hgca_core.drive(scans, out, poses=poses, samples=2, seed=3, weights=str(drive_weights), **SMALL)
    return out, doc


def test_every_tile_once_and_one_merged_mesh_per_sample(finished):
    out, doc = finished
    tiles = doc["tiles"]
    assert doc["status"] == "complete" and len(tiles) == 5
    assert [t["index"] for t in tiles] == list(range(5)) and all(t["status"] == "done" for t in tiles)
    assert all(t["run"] == 1 for t in tiles) and doc["timings"]["tiles_computed"] == 5
    assert len(list((out / "cache").glob("*.npz"))) == 5 == len({t["key"] for t in tiles})
    names = sorted(f"{i}_s{k}.ply" for i in range(5) for k in (0, 1))
    assert sorted(p.name for p in (out / "tiles").iterdir()) == names
    assert [t["seeds"] for t in tiles] == [[3 + 2 * i, 4 + 2 * i] for i in range(5)]
    # phase two (odd tiles) started from their finished neighbours' cells; phase one from the input alone
    assert all((t["fixed_cells"][0] > 0) == (t["index"] % 2 == 1) for t in tiles)
    assert tiles[1]["conditioned_on"] == [0, 2] and tiles[0]["conditioned_on"] == []
    on_disk = json.loads((out / "drive.json").read_text())
    assert on_disk["status"] == "complete" and on_disk["tiles"] == tiles
    assert [Path(p).name for p in doc["outputs"]] == ["drive_s0.ply", "drive_s1.ply"]
    s0, s1 = (read_ply(p) for p in doc["outputs"])
    assert len(s0[1]) > 1000 and not (len(s0[1]) == len(s1[1]) and np.array_equal(s0[0], s1[0])), "samples differ"
    xyz, faces, dist = s0
    assert len(dist) == len(xyz) and np.all(dist >= 0)
    assert xyz[:, 0].min() > -6.5 - 1 and xyz[:, 0].max() < 46.5 + 1, "world coordinates"


def test_merged_mesh_has_no_doubled_overlap(finished):
    from hgca_core.geometry.region import Region
    from hgca_core.tiling.merge import tile_piece
    from hgca_core.tiling.store import DriveStore

    out, doc = finished
    store = DriveStore(out)
    pieces = [tile_piece(store.load(t["key"])["samples"][0], Region.from_tuple(t["region"])) for t in doc["tiles"]]
    offsets = np.cumsum([0] + [len(p.vertices) for p in pieces])
    union = (np.concatenate([p.vertices for p in pieces]),
             np.concatenate([p.faces + o for p, o in zip(pieces, offsets)]))
    assert doubled_faces(*union) > 1000, "uncut tiles repeat their overlaps (so the checks below can fail)"
    xyz, faces, _ = read_ply(out / "drive_s0.ply")
    assert doubled_faces(xyz, faces) == 0
    assert len(faces) < len(union[1]) - 1000
    # the tile files are the parts each tile owns: together they are the merged mesh, nothing doubled
    parts = [read_ply(out / "tiles" / f"{i}_s0.ply") for i in range(5)]
    offsets = np.cumsum([0] + [len(m[0]) for m in parts])
    tiled = (np.concatenate([m[0] for m in parts]), np.concatenate([m[1] + o for m, o in zip(parts, offsets)]))
    assert doubled_faces(*tiled) == 0 and len(tiled[1]) == len(faces)


def test_rerun_keeps_every_tile_and_a_new_seed_recomputes_all(finished, flat_drive, drive_weights, tmp_path):
    import shutil

    out, first = tmp_path / "drive", finished[1]
    shutil.copytree(finished[0], out, copy_function=shutil.copy2)     # the shared drive stays as it was
    scans, poses = flat_drive
    mtimes = {p.name: p.stat().st_mtime_ns for p in (out / "cache").iterdir()}
    merged = (out / "drive_s0.ply").read_bytes()
    again = hgca_core.drive(scans, out, poses=poses, samples=2, seed=3, weights=str(drive_weights), **SMALL)
    assert again["runs"] == 2 and again["timings"]["tiles_computed"] == 0
    assert [t["run"] for t in again["tiles"]] == [1] * 5
    assert {p.name: p.stat().st_mtime_ns for p in (out / "cache").iterdir()} == mtimes
    assert (out / "drive_s0.ply").read_bytes() == merged
    other = hgca_core.drive(scans, out, poses=poses, samples=2, seed=4, weights=str(drive_weights), **SMALL)
    assert other["timings"]["tiles_computed"] == 5 and not {t["key"] for t in other["tiles"]} & set(
        t["key"] for t in first["tiles"])


def test_no_seams_runs_tiles_unconditioned(flat_drive, drive_weights, tmp_path):
    scans, poses = flat_drive
    doc = hgca_core.drive(scans[:5], tmp_path / "d", poses=poses, seams=False, weights=str(drive_weights), **SMALL)
    assert all(t["fixed_cells"] == [0] and t["conditioned_on"] == [] for t in doc["tiles"])


def test_georeferenced_drive_is_the_same_drive_moved(drive_weights, tmp_path):
    offset = np.array([512_346.0, 5_612_346.0, 130.0])
    near = write_drive(tmp_path / "near", length=16.0, slope=0.05)
    far = write_drive(tmp_path / "far", length=16.0, slope=0.05, offset=offset)
    a = hgca_core.drive(near[0], tmp_path / "a", poses=near[1], weights=str(drive_weights), **SMALL)
    b = hgca_core.drive(far[0], tmp_path / "b", poses=far[1], weights=str(drive_weights), **SMALL)
    for ta, tb in zip(a["tiles"], b["tiles"]):
        assert np.allclose(np.array(tb["region"][:3]) - offset, ta["region"][:3], atol=1e-6)
    va, fa, _ = read_ply(a["outputs"][0])
    vb, fb, _ = read_ply(b["outputs"][0])          # world coordinates, float64 in the file (io.georef)
    assert np.array_equal(fa, fb) and np.abs(vb - offset - va).max() < 1e-4


# In the environment of every CLI this module starts, so its tests find their own drive's Ray processes (`own_ray`)
# and never another run's on the machine: a user's drive, another pytest worker's.
TAG = uuid.uuid4().hex


def _cli(*args):
    env = {**os.environ, "HGCA_TEST_TAG": TAG,
           "PYTHONPATH": os.pathsep.join([str(Path(hgca_core.__file__).parents[1]), os.environ.get("PYTHONPATH", "")])}
    return subprocess.Popen([sys.executable, "-m", "hgca_core.cli", "drive", *map(str, args)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def own_ray(p, names: tuple[str, ...] = ("ray::tile_task",)) -> bool:
    """A process of a drive this module started whose command line names one of `names` (by default a Ray worker
    running a tile). Ray's head processes and workers inherit the CLI's environment; its agents set their titles
    over theirs, so they cannot be told apart and are not counted."""
    import psutil

    try:
        return any(n in " ".join(p.cmdline()) for n in names) and p.environ().get("HGCA_TEST_TAG") == TAG
    except psutil.Error:
        return False


def done_tiles(out: Path) -> int:
    try:
        return sum(t["status"] == "done" for t in json.loads((out / "drive.json").read_text())["tiles"])
    except (OSError, ValueError, KeyError):
        return 0


def test_resume_after_being_killed_halfway(tmp_path, drive_weights):
    """SIGKILL after two tiles (the hardest stop: nothing runs after it; the CLI's SIGINT / SIGTERM handler ends
    the process the same way, at once); the rerun computes only the rest."""
    sig = signal.SIGKILL
    scans, poses = write_drive(tmp_path / "scans", length=60.0)
    out = tmp_path / "drive"
    args = [*scans, "--poses", poses, "--out", out, "--weights", drive_weights, *CLI_SMALL, "--progress", "none"]
    proc = _cli(*args)
    deadline = time.time() + 240
    while done_tiles(out) < 2 and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    proc.send_signal(sig)
    proc.communicate(timeout=60)
    first = json.loads((out / "drive.json").read_text())
    # nothing ran after the kill: drive.json is the one the last finished tile wrote
    assert proc.returncode == -sig and first["status"] == "running"
    kept = {t["key"]: (out / "cache" / f"{t['key']}.npz").stat().st_mtime_ns
            for t in first["tiles"] if t["status"] == "done"}
    n = len(first["tiles"])
    assert 2 <= len(kept) < n == 7
    assert (out / ".lock").is_file(), "the killed run's lock file stays; its lock went with the process"
    rerun = _cli(*args)
    _, err = rerun.communicate(timeout=300)
    assert rerun.returncode == 0, err[-2000:]
    doc = json.loads((out / "drive.json").read_text())
    assert doc["status"] == "complete" and doc["timings"]["tiles_computed"] == n - len(kept)
    assert all((t["run"] == 1) == (t["key"] in kept) for t in doc["tiles"])
    assert {k: (out / "cache" / f"{k}.npz").stat().st_mtime_ns for k in kept} == kept
    assert len(list((out / "cache").glob("*.npz"))) == n and (out / "drive_s0.ply").is_file()
    assert not list(out.rglob(".*.tmp")), "temp files of the killed run are gone"


@pytest.mark.slow   # several Ray workers: `make test-slow` (CI runs it)
def test_ray_two_workers_survive_a_killed_worker(finished, flat_drive, drive_weights, tmp_path):
    """`--workers 2` on a local Ray: one tile's worker is killed while it runs; Ray retries that tile, and the drive
    ends with every tile exactly once and the very meshes the in-process run made (same plan, same keys)."""
    pytest.importorskip("ray")
    import psutil

    local_out, local = finished
    scans, poses = flat_drive
    out = tmp_path / "ray"
    proc = _cli(*scans, "--poses", poses, "--out", out, "--weights", drive_weights, *CLI_SMALL, "--samples", 2,
                "--seed", 3, "--workers", 2, "--progress", "none")
    killed, deadline = None, time.time() + 240
    while killed is None and proc.poll() is None and time.time() < deadline:
        for p in psutil.process_iter():
            if own_ray(p):
                os.kill(p.pid, signal.SIGKILL)
                killed = p.pid
                break
        time.sleep(0.05)
    _, err = proc.communicate(timeout=300)
    assert killed is not None, "a tile task was running and its worker got killed"
    assert proc.returncode == 0, err[-3000:]
    doc = json.loads((out / "drive.json").read_text())
    assert doc["engine"] == "ray" and doc["status"] == "complete" and doc["timings"]["tiles_computed"] == 5
    assert [t["index"] for t in doc["tiles"]] == list(range(5)) and all(t["run"] == 1 for t in doc["tiles"])
    assert sorted(p.name for p in (out / "cache").iterdir()) == sorted(f"{t['key']}.npz" for t in local["tiles"])
    assert len({t["worker"] for t in doc["tiles"]}) >= 2, "tiles ran in more than one worker process"
    assert str(killed) not in {t["worker"].split(":")[-1] for t in doc["tiles"]}, "the killed worker finished nothing"
    for k in (0, 1):
        assert (out / f"drive_s{k}.ply").read_bytes() == (local_out / f"drive_s{k}.ply").read_bytes()


def test_ctrl_c_in_a_library_call_marks_the_drive_interrupted(drive_weights, tmp_path, monkeypatch):
    from hgca_core.tiling import runners

    scans, poses = write_drive(tmp_path / "scans", length=20.0)
    real, calls = runners.complete_tile, []

    def second_is_interrupted(*args):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args)

    monkeypatch.setattr(runners, "complete_tile", second_is_interrupted)
    with pytest.raises(KeyboardInterrupt):
        hgca_core.drive(scans, tmp_path / "d", poses=poses, weights=str(drive_weights), **SMALL)
    doc = json.loads((tmp_path / "d" / "drive.json").read_text())
    assert doc["status"] == "interrupted" and [t["status"] for t in doc["tiles"]] == ["done", "pending", "pending"]
    monkeypatch.setattr(runners, "complete_tile", real)
    again = hgca_core.drive(scans, tmp_path / "d", poses=poses, weights=str(drive_weights), **SMALL)
    assert again["status"] == "complete" and again["timings"]["tiles_computed"] == 2


def test_sigterm_on_ray_stops_ray_and_exits_143(flat_drive, drive_weights, tmp_path):
    """ray.init puts an aborting SIGTERM handler in place (exit 134 and a crash report); the drive takes the
    signal back, stops its Ray and leaves the CLI's one line and exit status."""
    pytest.importorskip("ray")
    import psutil

    start = time.time()
    scans, poses = flat_drive
    proc = _cli(*scans, "--poses", poses, "--out", tmp_path / "d", "--weights", drive_weights, *CLI_SMALL,
                "--workers", 2, "--progress", "none")
    deadline = time.time() + 240
    while proc.poll() is None and time.time() < deadline and not any(map(own_ray, psutil.process_iter())):
        time.sleep(0.1)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143 and "hgca drive: terminated (SIGTERM)" in err, err[-2000:]
    doc = json.loads((tmp_path / "d" / "drive.json").read_text())
    assert doc["status"] == "interrupted" and "SIGTERM" in doc["error"], "not left 'running'"
    time.sleep(2)
    left = [p for p in psutil.process_iter(["create_time"]) if p.info["create_time"] >= start
            and own_ray(p, ("raylet", "gcs_server", "ray::"))]
    assert not left, [" ".join(p.cmdline())[:80] for p in left]


def test_without_ray_one_worker_runs_in_process_and_more_say_what_is_missing(drive_weights, tmp_path, capsys,
                                                                            monkeypatch):
    from hgca_core.cli import main

    monkeypatch.setitem(sys.modules, "ray", None)          # `import ray` raises ImportError, as if not installed
    scans, poses = write_drive(tmp_path / "scans", length=8.0)
    common = ["drive", *map(str, scans), "--poses", str(poses), "--weights", str(drive_weights), *CLI_SMALL,
              "--progress", "jsonl"]
    assert main([*common, "--out", str(tmp_path / "one")]) == 0
    assert json.loads(capsys.readouterr().out.splitlines()[-1])["stage"] == "done"
    assert json.loads((tmp_path / "one" / "drive.json").read_text())["engine"] == "local"
    assert main([*common, "--out", str(tmp_path / "two"), "--workers", "2"]) == 2
    err = capsys.readouterr().err
    assert "Ray is not installed" in err and "hgca[ray]" in err and not (tmp_path / "two").exists()


def test_bad_input_is_one_clear_error_and_writes_nothing(flat_drive, drive_weights, tmp_path, capsys):
    from hgca_core.cli import main

    scans, poses = flat_drive
    bare = tmp_path / "bare.npz"
    np.savez(bare, points=np.random.default_rng(0).normal(size=(100, 3)))
    cases = [([bare, "--out", tmp_path / "a"], "no origin"),
             ([*scans, "--poses", poses, "--out", tmp_path / "b", "--overlap", "50"], "overlap"),
             ([scans[0], bare, "--poses", poses, "--out", tmp_path / "c"], "no pose for scan")]
    (tmp_path / "file").write_text("x")
    cases.append(([*scans, "--poses", poses, "--out", tmp_path / "file"], "not a folder"))
    for args, message in cases:
        rc = main(["drive", *map(str, args), "--weights", str(drive_weights), "--stage", "coarse",
                   "--progress", "jsonl"])
        out, err = capsys.readouterr()
        assert rc == 2 and message in err and "Traceback" not in err, err
        assert json.loads(out.splitlines()[-1])["stage"] == "error"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bare.npz", "file"]


def test_a_tile_in_this_process_reports_its_chain_steps(flat_drive, drive_weights, tmp_path):
    """`--progress jsonl` on one worker: between the tile records come `tile-step` records of the running tile's
    chain (T1 steps a sample), so a bar moves within a tile, not only between tiles."""
    scans, poses = flat_drive
    proc = _cli(*scans, "--poses", poses, "--out", tmp_path / "d", "--weights", drive_weights, *CLI_SMALL,
                "--progress", "jsonl")
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err[-2000:]
    records = [json.loads(line) for line in out.splitlines()]
    steps = [r for r in records if r["stage"] == "tile-step"]
    assert steps and {r["chain"] for r in steps} >= {"coarse"}
    first = [r for r in steps if r["tile"] == 0 and r["chain"] == "coarse"]
    assert [r["step"] for r in first] == list(range(1, 4)) and all(r["total"] == 3 for r in first)
    done = [i for i, r in enumerate(records) if r["stage"] == "tile" and r.get("state") == "done"]
    assert any(r["stage"] == "tile-step" for r in records[:done[0]])

"""`hgca complete` on georeferenced, degenerate and mis-flagged input (issue 11, items 3, 4 and 7).

Runs the real CLI in a subprocess with the small untrained weights of conftest (`small_weights`, 3 steps),
so each completion takes a few seconds; the coarse stage is enough to check where the mesh lands.
"""
from __future__ import annotations

import hashlib
import json
import struct
import subprocess
import sys

import numpy as np
import pytest

from hgca_testdata import UTM_OFFSETS, tiny_sample, write_las

MM = 1e-3


def hgca(*args, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hgca_core.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


def clear_error(res: subprocess.CompletedProcess, *needles: str) -> None:
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])
    assert "Traceback" not in res.stderr, res.stderr
    for needle in needles:
        assert needle in res.stderr, res.stderr


@pytest.mark.parametrize("place", sorted(UTM_OFFSETS))
def test_completion_of_a_utm_las_lands_on_its_grid_to_the_mm(small_weights, tmp_path, place):
    """A LAS at x ~ 500 km, y ~ 5,000 km or ~ 10,000 km: the coarse mesh's vertices are cell corners of the
    region's 20 cm grid, in world coordinates, within 1 mm (float32 world coordinates put them on a 0.5 m or
    1 m grid), for the .npz the add-on reads and for .ply."""
    s = tiny_sample(3)
    origin = np.array(UTM_OFFSETS[place])
    held = write_las(tmp_path / "scan.las", s["input_points"].astype(np.float64) + origin)
    lo = origin + np.array([0.0, 0.0, 0.0])  # the tiny sample's region is [0, 6] x [0, 6] x [-1, 3] around it
    region = f"--region={lo[0] + 3!r},{lo[1] + 3!r},{lo[2] + 1!r},6,6,4"
    for ext in (".npz", ".ply"):
        res = hgca("complete", tmp_path / "scan.las", "-o", tmp_path / f"out{ext}", "--weights", small_weights,
                   "--stage", "coarse", "--t1", 2, region, "--progress", "none")
        assert res.returncode == 0, res.stderr[-2000:]
    with np.load(tmp_path / "out_s0.npz") as z:
        assert z["offset"].dtype == np.float64
        world = z["vertices"].astype(np.float64) + z["offset"]
    assert len(world) > 100
    from plyfile import PlyData

    v = PlyData.read(str(tmp_path / "out_s0.ply"))["vertex"].data
    from_ply = np.column_stack([v["x"], v["y"], v["z"]]).astype(np.float64)
    np.testing.assert_allclose(np.sort(from_ply, axis=0), np.sort(world, axis=0), rtol=0, atol=MM)
    corner = lo - np.array([0.0, 0.0, 1.0])  # the region's minimum corner (centre - size / 2)
    cells = (world - corner + 0.05) / 0.2  # coarse vertices sit at k * 0.2 - 0.05 in the region frame
    assert np.abs(cells - np.round(cells)).max() * 0.2 < MM
    inside = (world > corner - 0.3) & (world < corner + np.array([6, 6, 4]) + 0.3)
    assert inside.all()
    assert np.abs(held - origin).max() < 10  # the scan really is at that place


@pytest.mark.parametrize("case, needles", [
    ("one point", ["too few input points", "1 point(s)"]),
    ("identical", ["too few input points", "50000 point(s)", "all at the same spot"]),
    ("las scale 0", ["corrupt LAS header", "x scale is 0"]),
    ("las huge count", ["truncated or corrupt", "4294967295 points"]),
])
def test_degenerate_input_is_refused_with_its_reason(small_weights, tmp_path, case, needles):
    """Never an empty mesh with exit 0: the reason comes first and nothing is written."""
    if case == "one point":
        scan = tmp_path / "one.npz"
        np.savez(scan, points=np.array([[1.0, 2.0, 0.5]]))
    elif case == "identical":
        scan = tmp_path / "same.npz"
        np.savez(scan, points=np.tile([[1.0, 2.0, 0.5]], (50_000, 1)))
    else:
        scan = tmp_path / "bad.las"
        write_las(scan, tiny_sample(1)["input_points"].astype(np.float64))
        raw = bytearray(scan.read_bytes())
        if case == "las scale 0":
            struct.pack_into("<d", raw, 131, 0.0)  # x scale factor of the LAS 1.2 public header
        else:
            struct.pack_into("<I", raw, 107, 0xFFFFFFFF)  # legacy point count
            raw = raw[:400]
        scan.write_bytes(bytes(raw))
    res = hgca("complete", scan, "-o", tmp_path / "out.npz", "--weights", small_weights, "--stage", "coarse",
               "--progress", "jsonl")
    clear_error(res, *needles)
    assert "too large" not in res.stderr
    assert json.loads(res.stdout.splitlines()[-1])["stage"] == "error"
    assert not list(tmp_path.glob("out*"))


@pytest.mark.parametrize("argv, needles", [
    (["--t1", "-3"], ["argument --t1", "must be a whole number >= 0"]),
    (["--t2", "-1"], ["argument --t2", "must be a whole number >= 0"]),
    (["--t1", "two"], ["argument --t1", "not a whole number"]),
    (["--device", "tpu"], ["argument --device", "unknown device 'tpu'"]),
])
def test_bad_flags_are_clear_errors(tmp_path, argv, needles):
    np.savez(tmp_path / "s.npz", points=np.zeros((5, 3)))
    clear_error(hgca("complete", tmp_path / "s.npz", "-o", tmp_path / "o.npz", *argv), *needles)
    assert not list(tmp_path.glob("o*"))


def test_bench_and_eval_share_the_step_and_device_checks(tmp_path):
    clear_error(hgca("bench", "--t1", "-1", "--out", tmp_path), "argument --t1")
    clear_error(hgca("bench", "--device", "tpu", "--out", tmp_path), "unknown device")
    clear_error(hgca("eval", "--t2", "-2", "--data", tmp_path), "argument --t2")


@pytest.mark.slow   # minutes on 2 cores: `make test-slow` (CI runs it)
def test_bench_times_the_weights_it_is_given(small_weights, tmp_path, capsys):
    """`hgca bench --weights` runs the given file (its own 3 steps, not the shipped file's 30) and names it by
    sha256 in the result; a file that is not weights is a clear error before any run writes anything."""
    res = hgca("bench", "--widths", "", "--stage", "coarse", "--weights", small_weights, "--out", tmp_path / "r",
               "--name", "b")
    assert res.returncode == 0, res.stderr[-2000:]
    result = json.loads((tmp_path / "r" / "b.json").read_text())
    assert result["weights"] == {"coarse": str(small_weights)}
    assert result["weights_sha256"]["coarse"] == hashlib.sha256(small_weights.read_bytes()).hexdigest()
    (row,) = result["rows"]
    assert "error" not in row and row["steps"] == {"coarse": 3} and row["coarse_cells"] > 0
    assert f"coarse {small_weights.name} (sha256 {result['weights_sha256']['coarse'][:8]})" in res.stdout
    from hgca_core.cli import main

    def refused(*args) -> subprocess.CompletedProcess:
        """The refusals run the CLI in this process (exit status and stderr as `hgca` gives them): each is
        decided before any work, and four fresh processes cost ~20 s."""
        capsys.readouterr()
        code = main(["bench", *map(str, args)])
        return subprocess.CompletedProcess(args, code, *capsys.readouterr())

    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not weights")
    clear_error(refused("--widths", "", "--weights", bad, "--out", tmp_path / "r2"), "bad.pt")
    assert not (tmp_path / "r2").exists()
    named_like_a_result = tmp_path / "r" / "c.json"
    named_like_a_result.write_bytes(small_weights.read_bytes())
    clear_error(refused("--widths", "", "--weights", named_like_a_result, "--out", tmp_path / "r", "--name", "c"),
                "would overwrite an input")
    assert named_like_a_result.read_bytes() == small_weights.read_bytes()
    a_file = tmp_path / "r" / "b.md"                  # --out naming a file: refused, the file kept
    kept = a_file.read_bytes()
    clear_error(refused("--widths", "", "--weights", small_weights, "--out", a_file), "is not a folder")
    assert a_file.read_bytes() == kept
    clear_error(refused("--widths", "", "--weights", small_weights, "--out", a_file / "sub"),
                "cannot make the output folder")


def test_t1_zero_means_the_weights_own_steps(small_weights, tmp_path):
    """`--t1 0` is what leaving it out does: the weights' step count (3 for these), not zero steps."""
    scan = tmp_path / "scan.npz"
    s = tiny_sample(3)
    np.savez(scan, points=s["input_points"].astype(np.float64))
    res = hgca("complete", scan, "-o", tmp_path / "o.npz", "--weights", small_weights, "--stage", "coarse",
               "--t1", 0, "--region", "3,3,1,6,6,4", "--progress", "jsonl")
    assert res.returncode == 0, res.stderr[-2000:]
    totals = {r["total"] for r in map(json.loads, res.stdout.splitlines()) if r["stage"] == "coarse"}
    assert totals == {3}


def test_python_api_refuses_negative_steps(small_weights):
    import hgca_core

    pts = tiny_sample(3)["input_points"].astype(np.float64)
    with pytest.raises(hgca_core.InputError, match="t1 must be a whole number >= 0"):
        hgca_core.complete(pts, region=hgca_core.Region.parse("3,3,1,6,6,4"), stage="coarse", t1=-2,
                           weights=small_weights)


@pytest.fixture
def full_disk(tmp_path):
    """A folder on a 16 kB tmpfs (a real ENOSPC); where mounting is not allowed, the test is skipped."""
    from hgca_testdata import small_tmpfs

    with small_tmpfs(tmp_path / "full", "16k") as root:
        yield root


def one_disk_full_line(res: subprocess.CompletedProcess, command: str) -> None:
    """Exit 2 and exactly one line, the error, naming the full disk (no second failure on a closed file)."""
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"hgca {command}: error: "), res.stderr
    assert "no space left on the device" in lines[0], res.stderr


def test_disk_full_while_writing_is_one_line_and_leaves_nothing(small_weights, tmp_path, full_disk):
    big = tmp_path / "big.npz"
    np.savez(big, points=np.random.default_rng(0).uniform(0, 20, (20_000, 3)))
    one_disk_full_line(hgca("read", big, "-o", full_disk / "x.npz"), "read")
    assert list(full_disk.iterdir()) == []
    scan = tmp_path / "scan.npz"
    np.savez(scan, points=tiny_sample(3)["input_points"].astype(np.float64))
    for out in ("x.npz", "x.ply"):
        res = hgca("complete", scan, "-o", full_disk / out, "--weights", small_weights, "--stage", "coarse",
                   "--region", "3,3,1,6,6,4", "--samples", "2", "--progress", "none")
        one_disk_full_line(res, "complete")
        assert list(full_disk.iterdir()) == [], "no sample, no temp file"


@pytest.mark.parametrize("command", ["read", "complete", "complete --samples 2", "poses"])
def test_an_output_name_too_long_is_refused_before_any_input_is_read(tmp_path, monkeypatch, capsys, command):
    """A 250-character `-o` fits the file system, but its sample names (`_s0`) or its temp file do not: that
    failed only after every stage ran. Now the reader is never reached."""
    import hgca_core.io.sequence as sequence
    from hgca_core.cli import main

    called = []

    def reader(*args, **kwargs):
        called.append(args)
        raise AssertionError("read before the outputs were checked")

    monkeypatch.setattr(sequence, "read_inputs", reader)
    monkeypatch.setattr(sequence, "open_sequence", reader)
    np.savez(tmp_path / "s.npz", points=np.zeros((50, 3)))
    name, *extra = command.split()
    if name == "poses":
        (tmp_path / "seq").mkdir()
        argv = ["poses", str(tmp_path / "seq"), "-o", str(tmp_path / ("a" * 246 + ".json"))]
    else:
        argv = [name, str(tmp_path / "s.npz"), *extra, "-o", str(tmp_path / ("a" * 246 + ".npz"))]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "too long" in err and "Traceback" not in err, err
    assert called == []
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["s.npz"] + (["seq"] if name == "poses" else []))


def test_fifty_million_points_under_a_3_gib_limit_are_refused_up_front_with_the_figure(tmp_path):
    """The point count of a KITTI .bin is its size / 16: 800 MB (sparse here) is 50 M points, ~3.8 GiB to read."""
    import resource

    scan = tmp_path / "fifty.bin"
    with open(scan, "wb") as f:
        f.truncate(50_000_000 * 16)

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (3 * 2**30, 3 * 2**30))

    for command in ("read", "complete"):
        out = tmp_path / ("o.npz" if command == "read" else "m.ply")
        res = subprocess.run([sys.executable, "-m", "hgca_core.cli", command, str(scan), "-o", str(out)],
                             capture_output=True, text=True, timeout=300, preexec_fn=limit)
        clear_error(res, "about 50,000,000 points", "GiB to read", "address-space limit")
        assert sorted(p.name for p in tmp_path.iterdir()) == ["fifty.bin"]


def test_point_counts_come_from_the_headers(tmp_path):
    from hgca_core.io.memory import point_count_hint
    from hgca_core.io import write_points

    pts = tiny_sample(3)["input_points"].astype(np.float64)
    write_las(tmp_path / "a.las", pts + [500_000.0, 5_000_000.0, 0.0])
    write_points(tmp_path / "a.ply", pts)
    np.save(tmp_path / "a.npy", pts)
    (tmp_path / "a.pcd.bin").write_bytes(b"\0" * 20 * 7)
    for name in ("a.las", "a.ply", "a.npy"):
        assert point_count_hint([str(tmp_path / name)]) == len(pts), name
    assert point_count_hint([str(tmp_path / "a.pcd.bin"), str(tmp_path)]) == 7

"""Hostile classes: inputs that do not belong together, the same data by two routes, readers that go away and
numbers at the edges. Each case once gave a silently wrong result (one street from two CRSs, feet on metre cells,
another scan's sensor for an originless scan's rays, another mesh from `hgca read`'s .npz than from its folder,
exit 0 and no mesh when the progress reader left, an IndexError for a thin region, a refused --scans-per-tile).

Completions are tiny (--stage coarse, 4 coarse steps) and shared through module fixtures: five completions and
one drive in all."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hgca_core.cli import main
from hgca_core.errors import InputError

sys.path.insert(0, str(Path(__file__).resolve().parent / "drive"))
from drive_data import write_drive, write_kitti  # noqa: E402

laspy = pytest.importorskip("laspy")
from laspy.vlrs.known import WktCoordinateSystemVlr  # noqa: E402
from builders import geokeys  # noqa: E402

FAST = ["--stage", "coarse", "--t1", "4", "--device", "cpu"]
SMALL_REGION = "8,0,1,9.6,9.6,4"
CLOSED = "the progress stream is closed"
FEET_WKT = ('PROJCS["NAD83 / New York Long Island (ftUS)",GEOGCS["NAD83",DATUM["North_American_Datum_1983",'
            'SPHEROID["GRS 1980",6378137,298.257222101]],UNIT["degree",0.0174532925199433]],'
            'PROJECTION["Lambert_Conformal_Conic_2SP"],UNIT["US survey foot",0.3048006096012192,'
            'AUTHORITY["EPSG","9003"]]]')


def cli(monkeypatch, capsys, *argv) -> tuple[int, str, str]:
    monkeypatch.setattr(sys, "argv", ["hgca"])
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def hgca(*argv) -> list[str]:
    return [sys.executable, "-m", "hgca_core.cli", *[str(a) for a in argv]]


def street_las(path: Path, vlrs=(), shift: float = 0.0) -> Path:
    """A LAS of a 20 x 20 m patch of ground with a wall (enough points to complete), UTM-sized coordinates."""
    rng = np.random.default_rng(len(path.name))
    ground = np.c_[rng.uniform(0, 20, (6000, 2)), np.zeros(6000)]
    wall = np.c_[rng.uniform(0, 20, 3000), np.full(3000, 15.0), rng.uniform(0, 3, 3000)]
    pts = np.concatenate([ground, wall]) + [500000.0 + shift, 4000000.0, 100.0]
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = [0.001] * 3, [500000.0, 4000000.0, 0.0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts.T
    for vlr in vlrs:
        las.vlrs.append(vlr)
    las.write(str(path))
    return path


# --- 1. files that do not belong together -------------------------------------------------------------------

def test_scans_in_two_crss_are_refused_naming_both(tmp_path, monkeypatch, capsys):
    a = street_las(tmp_path / "utm33.las", [geokeys((1024, 1), (3072, 32633))])
    b = street_las(tmp_path / "utm34.las", [geokeys((1024, 1), (3072, 32634))], shift=10.0)
    for argv in (["read", a, b, "-o", tmp_path / "both.npz"], ["complete", a, b, "-o", tmp_path / "m.ply", *FAST],
                 ["drive", a, b, "-o", tmp_path / "drive", "--stage", "coarse"]):
        code, _, err = cli(monkeypatch, capsys, *argv)
        assert code == 2, err
        line = err.strip().splitlines()[-1]
        assert "different CRSs" in line and "EPSG:32633" in line and "EPSG:32634" in line, line
        assert "utm33.las" in line and "utm34.las" in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["utm33.las", "utm34.las"]


def test_read_writes_the_crs_into_its_npz_and_it_round_trips(tmp_path, monkeypatch, capsys):
    a = street_las(tmp_path / "a.las", [geokeys((1024, 1), (3072, 32633))])
    b = street_las(tmp_path / "b.las", [geokeys((1024, 1), (3072, 32633))], shift=5.0)
    code, out, err = cli(monkeypatch, capsys, "read", a, b, "-o", tmp_path / "ab.npz", "--json")
    assert code == 0 and json.loads(out)["crs"] == "EPSG:32633", err
    with np.load(tmp_path / "ab.npz") as z:
        assert str(z["crs"][()]) == "EPSG:32633"
    code, out, err = cli(monkeypatch, capsys, "read", tmp_path / "ab.npz", "-o", tmp_path / "again.npz", "--json")
    assert code == 0 and json.loads(out)["crs"] == "EPSG:32633", err
    other = street_las(tmp_path / "c.las", [geokeys((1024, 1), (3072, 32634))])
    code, _, err = cli(monkeypatch, capsys, "read", tmp_path / "ab.npz", other, "-o", tmp_path / "no.npz")
    assert code == 2 and "EPSG:32633" in err and "EPSG:32634" in err and "ab.npz" in err, err


@pytest.mark.parametrize("vlrs, says", [
    ([geokeys((1024, 1), (3072, 2263))], "EPSG:2263"),                       # State Plane NY Long Island, ftUS
    ([WktCoordinateSystemVlr(FEET_WKT)], "US survey foot"),                   # a WKT without a code, in feet
    ([geokeys((1024, 1), (3072, 32767), (3076, 9002))], "foot (0.3048 m)"),  # user-defined, unit key: feet
], ids=["epsg2263", "wkt-feet", "unit-key"])
def test_feet_are_refused_for_completion_and_kept_by_read(tmp_path, monkeypatch, capsys, vlrs, says):
    """Feet on 20 cm cells would be a completion at 3.28 times the scale; `hgca read` keeps the file's numbers
    and says their unit in its .npz, whose completion is refused the same way."""
    las = street_las(tmp_path / "feet.las", vlrs)
    code, _, err = cli(monkeypatch, capsys, "complete", las, "-o", tmp_path / "m.ply", *FAST)
    assert code == 2 and says in err and "metres" in err and "reproject" in err, err
    code, _, err = cli(monkeypatch, capsys, "read", las, "-o", tmp_path / "feet.npz")
    assert code == 0, err
    with np.load(tmp_path / "feet.npz") as z:
        np.testing.assert_allclose(z["points"].min(axis=0) + z["offset"], laspy.read(str(las)).xyz.min(axis=0))
    code, _, err = cli(monkeypatch, capsys, "complete", tmp_path / "feet.npz", "-o", tmp_path / "m.ply", *FAST)
    assert code == 2 and ("foot" in err or "feet (" in err) and "feet.npz" in err and "metres" in err, err
    assert not list(tmp_path.glob("m_s*"))


def test_a_scan_without_origin_beside_one_with_origin_is_refused(tmp_path, monkeypatch, capsys):
    """Without poses, the originless scan's rays would come from the other scan's sensor."""
    from hgca_core.io import read_scans

    rng = np.random.default_rng(3)
    np.c_[rng.uniform(-5, 5, (500, 3)), rng.random(500)].astype("<f4").tofile(tmp_path / "sensor.bin")  # origin 0
    np.savetxt(tmp_path / "plain.xyz", rng.uniform(-5, 5, (500, 3)))
    with pytest.raises(InputError, match="no sensor origin but .*sensor.bin has one") as info:
        read_scans([tmp_path / "sensor.bin", tmp_path / "plain.xyz"])
    assert info.value.path == str(tmp_path / "plain.xyz")
    code, _, err = cli(monkeypatch, capsys, "read", tmp_path / "plain.xyz", tmp_path / "sensor.bin",
                       "-o", tmp_path / "o.npz")
    assert code == 2 and "plain.xyz: this scan has no sensor origin" in err, err
    # with poses every scan has its pose's origin: accepted
    poses = {"scans": [{"file": n, "pose": np.eye(4).tolist()} for n in ("sensor.bin", "plain.xyz")]}
    (tmp_path / "poses.json").write_text(json.dumps(poses))
    scan = read_scans([tmp_path / "sensor.bin", tmp_path / "plain.xyz"], poses=tmp_path / "poses.json")
    assert scan.origins.shape == (2, 3)


# --- 2. the same data by two routes ----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def kitti(tmp_path_factory) -> dict:
    """A KITTI-like folder, the .npz `hgca read` wrote from it, and both completed (a small region, the default
    region); the .npz's small-region run has stdout closed (`>&-`) and --progress jsonl, as a pipeline may."""
    root = tmp_path_factory.mktemp("kitti")
    write_kitti(root / "seq")
    done = subprocess.run(hgca("read", root / "seq", "-o", root / "seq.npz"), capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    runs = {}
    for name, source, extra in (("folder_small", root / "seq", ["--region", SMALL_REGION]),
                                ("npz_small", root / "seq.npz", ["--region", SMALL_REGION, "--progress", "jsonl"]),
                                ("folder_default", root / "seq", []), ("npz_default", root / "seq.npz", [])):
        argv = hgca("complete", source, "-o", root / f"{name}.ply", *FAST, *extra)
        if name == "npz_small":
            runs[name] = subprocess.run(["bash", "-c", 'exec "$@" >&-', "_", *argv], stderr=subprocess.PIPE,
                                        text=True, timeout=600)
        else:
            runs[name] = subprocess.run([*argv, "--progress", "none"], capture_output=True, text=True, timeout=600)
    return {"root": root, "runs": runs}


def test_read_npz_carries_what_complete_needs(kitti):
    with np.load(kitti["root"] / "seq.npz") as z:
        assert z["points"].dtype == np.float64
        np.testing.assert_array_equal(np.unique(z["scan_index"]), np.arange(len(z["origins"])))


@pytest.mark.parametrize("region", ["small", "default"])
def test_npz_from_read_completes_like_its_folder(kitti, region):
    root, runs = kitti["root"], kitti["runs"]
    for name in (f"folder_{region}", f"npz_{region}"):
        assert runs[name].returncode == 0, runs[name].stderr
    a, b = (root / f"folder_{region}_s0.ply").read_bytes(), (root / f"npz_{region}_s0.ply").read_bytes()
    assert len(a) > 1000 and a == b


# --- 3. streams that go away ------------------------------------------------------------------------------------

def test_complete_with_stdout_closed_writes_its_mesh(kitti):
    run = kitti["runs"]["npz_small"]
    assert run.returncode == 0, run.stderr
    assert (kitti["root"] / "npz_small_s0.ply").stat().st_size > 1000
    assert run.stderr.count(CLOSED) == 1 and "AttributeError" not in run.stderr, run.stderr


def read_one_line_then_leave(argv: list[str]) -> tuple[int, str, str]:
    """Start `argv`, read the first progress line, close the pipe, wait: (exit code, first line, stderr)."""
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    first = proc.stdout.readline()
    proc.stdout.close()
    err = proc.stderr.read()
    return proc.wait(timeout=600), first, err


def test_complete_keeps_working_when_the_progress_reader_leaves(tmp_path):
    write_kitti(tmp_path / "seq")
    code, first, err = read_one_line_then_leave(hgca("complete", tmp_path / "seq", "-o", tmp_path / "m.ply",
                                                     "--region", SMALL_REGION, "--progress", "jsonl", *FAST))
    assert json.loads(first)["stage"] == "read"
    assert code == 0, err
    assert (tmp_path / "m_s0.ply").stat().st_size > 1000
    assert err.count(CLOSED) == 1 and "hgca complete: warning:" in err, err


def test_drive_keeps_working_when_the_progress_reader_leaves(tmp_path):
    paths, poses = write_drive(tmp_path / "in", length=8.0)
    out = tmp_path / "drive"
    code, first, err = read_one_line_then_leave(hgca("drive", *paths, "--poses", poses, "-o", out, "--size", "12.8",
                                                     "--overlap", "3.2", "--progress", "jsonl", *FAST))
    assert json.loads(first)["protocol"] == 1
    assert code == 0, err
    doc = json.loads((out / "drive.json").read_text())
    assert doc["status"] == "complete" and (out / "drive_s0.ply").stat().st_size > 1000, doc.get("status")
    assert err.count(CLOSED) == 1, err


def test_progress_to_a_closed_stream_is_dropped_once():
    import io
    import warnings

    from hgca_core.errors import HgcaWarning
    from hgca_core.progress import Progress

    stream = io.StringIO()
    progress = Progress("jsonl", stream=stream)
    progress("read", 0, 1)
    stream.close()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for step in range(3):
            progress("coarse", step, 3)
        progress.done(["m_s0.ply"])
    assert progress.lost and [w.category for w in caught] == [HgcaWarning]


def test_stderr_whose_reader_left_drops_writes_instead_of_failing():
    """`hgca drive ... 2>&1 | head -1` in bar mode: the tiles bar's next write met a closed pipe, and the drive
    ended with exit 0, status "failed" and no mesh."""
    from hgca_core.cli import _Survivor

    read, write = os.pipe()
    os.close(read)
    survivor = _Survivor(os.fdopen(write, "w"))
    for _ in range(3):
        survivor.write("tiles: 1/3\r" * 10000)
        survivor.flush()
    assert survivor._lost
    survivor.write("dropped")                       # the descriptor is /dev/null now: nothing fails
    survivor.flush()


# --- 4. numbers at the edges ------------------------------------------------------------------------------------

def test_thin_region_is_refused_naming_the_minimum(tmp_path, monkeypatch, capsys):
    from hgca_core.geometry.region import Region

    np.savetxt(tmp_path / "s.xyz", np.random.default_rng(0).uniform(-5, 5, (2000, 3)))
    code, _, err = cli(monkeypatch, capsys, "complete", tmp_path / "s.xyz", "-o", tmp_path / "m.ply",
                       "--region", "0,0,0,6.4,6.4,0.1", *FAST)
    assert code == 2 and "at least 0.2 m" in err and "z too thin" in err and "IndexError" not in err, err
    assert Region(np.zeros(3), np.array([0.2, 6.4, 4.0])).grid_shape(0.2) == (1, 32, 20)


def test_scans_per_tile_above_the_scan_count_means_all(tmp_path, monkeypatch, capsys):
    paths, poses = write_drive(tmp_path / "in", length=8.0)
    code, out, err = cli(monkeypatch, capsys, "drive", *paths, "--poses", poses, "--plan-only", "--json",
                         "--scans-per-tile", "20000")
    assert code == 0, err
    plan = json.loads(out)
    assert plan["tiles"] and all(t["scans"] == list(range(len(paths))) for t in plan["tiles"])
    from hgca_core.cli import build_parser

    drive = build_parser(["drive"])._subparsers._group_actions[0].choices["drive"]
    option = next(a for a in drive._actions if "--scans-per-tile" in a.option_strings)
    assert "means all of them" in option.help

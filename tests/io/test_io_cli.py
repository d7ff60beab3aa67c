"""`hgca info` and `hgca read` through the real CLI entry point."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest

from hgca_core.cli import main
from hgca_core.io.sensor_bin import EGO_RETURNS

REPO = Path(__file__).resolve().parents[2]


def run_cli(monkeypatch, capsys, *argv: str) -> tuple[int, str, str]:
    monkeypatch.setattr(sys, "argv", ["hgca"])  # main() rewrites sys.argv; monkeypatch restores it
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def scan_files(real_dir: Path) -> list[Path]:
    return sorted(p for p in real_dir.iterdir() if p.is_file() and p.suffix != ".md")  # av2/ is a folder


def expected_count(path: Path) -> int:
    if path.name.endswith(".pcd.bin"):
        return path.stat().st_size // 20
    return laspy.open(path).header.point_count


def test_info_every_real_file_json(real_dir, monkeypatch, capsys):
    files = scan_files(real_dir)
    assert len(files) >= 7
    code, out, _ = run_cli(monkeypatch, capsys, "info", "--json", *files)
    assert code == 0
    doc = json.loads(out)
    assert [f["file"] for f in doc["files"]] == [str(p) for p in files]
    for path, info in zip(files, doc["files"]):
        # every row of the file is either read or counted as dropped (the nuScenes car's own returns)
        assert info["points"] + sum(info["dropped"].values()) == expected_count(path), path.name
        if path.name.endswith(".pcd.bin"):
            assert info["format"] == "nuscenes" and 0 < info["dropped"][EGO_RETURNS] < info["points"]
            assert info["attributes"] == {"intensity": "float32", "ring": "uint16"}
            continue
        assert info["dropped"] == {}
        las = laspy.read(path)
        assert info["format"] == "las"
        assert info["las"]["header_point_count"] == las.header.point_count
        assert info["las"]["point_format"] == las.header.point_format.id
        assert info["las"]["version"] == f"{las.header.version.major}.{las.header.version.minor}"
        np.testing.assert_allclose(info["las"]["scale"], las.header.scales)
        np.testing.assert_allclose(info["las"]["offset"], las.header.offsets)
        np.testing.assert_allclose(info["bounds"]["min"], [las.x.min(), las.y.min(), las.z.min()])
        np.testing.assert_allclose(info["bounds"]["max"], [las.x.max(), las.y.max(), las.z.max()])
        assert info["attributes"]["intensity"] == "uint16"


@pytest.mark.parametrize("name", ["simple.las", "simple.copc.laz", "autzen_trim.laz",
                                  "nuscenes_lidar_top_1532402927647951.pcd.bin"])
def test_info_text(real_dir, monkeypatch, capsys, name):
    path = real_dir / name
    code, out, _ = run_cli(monkeypatch, capsys, "info", path)
    assert code == 0
    points = int(out.split("points:")[1].split()[0])
    dropped = int(out.split("dropped:")[1].split()[0]) if "dropped:" in out else 0
    assert points + dropped == expected_count(path)
    assert (dropped > 0) == name.endswith(".pcd.bin")
    assert "bounds min:" in out and "attributes: intensity" in out
    if name.endswith(".laz") or name.endswith(".las"):
        assert "scale:" in out and "offset:" in out and "header point count" in out
    if "copc" in name:
        assert "COPC 1.4, point format 7" in out


def test_info_bad_file_exit_2(tmp_path, monkeypatch, capsys):
    (tmp_path / "broken.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n")
    code, out, err = run_cli(monkeypatch, capsys, "info", tmp_path / "broken.ply")
    assert code == 2 and out == ""
    assert "broken.ply" in err and "Traceback" not in err


def test_read_command_accumulates_with_poses(tmp_path, monkeypatch, capsys):
    for name, pts in (("s0.bin", [[1, 0, 0]]), ("s1.bin", [[0, 0, 0], [0, 1, 0]])):
        np.column_stack([pts, np.full(len(pts), 0.5)]).astype(np.float32).tofile(tmp_path / name)
    poses = {"scans": [{"file": "s0.bin", "pose": np.eye(4).tolist()},
                       {"file": "s1.bin", "pose": [[1, 0, 0, 3], [0, 1, 0, 0], [0, 0, 1, 1.5], [0, 0, 0, 1]]}]}
    (tmp_path / "poses.json").write_text(json.dumps(poses))
    out = tmp_path / "acc.npz"
    code, stdout, _ = run_cli(monkeypatch, capsys, "read", tmp_path / "s0.bin", tmp_path / "s1.bin",
                              "--poses", tmp_path / "poses.json", "-o", out)
    assert code == 0 and "3 points" in stdout
    with np.load(out) as z:
        assert set(z.keys()) == {"points", "offset", "intensity", "scan_index", "origins"}
        assert z["points"].dtype == np.float64
        np.testing.assert_allclose(z["points"], [[1, 0, 0], [3, 0, 1.5], [3, 1, 1.5]])
        np.testing.assert_array_equal(z["scan_index"], [0, 1, 1])
        np.testing.assert_allclose(z["origins"], [[0, 0, 0], [3, 0, 1.5]])


def test_read_command_errors(tmp_path, monkeypatch, capsys):
    code, _, err = run_cli(monkeypatch, capsys, "read", tmp_path / "missing.las", "-o", tmp_path / "o.npz")
    assert code == 2 and "missing.las" in err and "not found" in err
    (tmp_path / "a.xyz").write_text("1 2 3\n")
    code, _, err = run_cli(monkeypatch, capsys, "read", tmp_path / "a.xyz", "-o", tmp_path / "o.ply")
    assert code == 2 and "o.ply" in err and ".npz" in err
    assert not (tmp_path / "o.npz").exists() and not (tmp_path / "o.ply").exists()


def test_installed_script_and_no_torch(real_dir, tmp_path):
    """The console script works, and info/read never import torch (the Blender add-on relies on that)."""
    exe = REPO / ".venv/bin/hgca"
    if not exe.exists():
        pytest.skip(f"console script not installed at {exe}")
    las = real_dir / "simple.laz"
    res = subprocess.run([str(exe), "info", str(las)], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and "points:     1065" in res.stdout
    code = (
        "import sys; from hgca_core.cli import main; "
        f"rc = main(['read', {str(las)!r}, '-o', {str(tmp_path / 'o.npz')!r}]); "
        "assert rc == 0; assert 'torch' not in sys.modules, 'torch imported'"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert res.returncode == 0, res.stderr
    res = subprocess.run([str(exe), "info", str(tmp_path / "nothing.ply")], capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 2 and "nothing.ply: file not found" in res.stderr and "Traceback" not in res.stderr


def test_read_command_says_what_it_left_out(real_dir, tmp_path, monkeypatch, capsys):
    """`hgca read` of the nuScenes sweep writes the points less the car's own returns and says how many it left."""
    path = real_dir / "nuscenes_lidar_top_1532402927647951.pcd.bin"
    code, out, _ = run_cli(monkeypatch, capsys, "read", path, "-o", tmp_path / "n.npz")
    assert code == 0
    with np.load(tmp_path / "n.npz") as data:
        kept = len(data["points"])
    left = int(out.split("left out ")[1].split()[0])
    assert kept + left == expected_count(path) and f"left out {left} {EGO_RETURNS}" in out


def test_read_json_says_what_it_wrote_and_left_out(real_dir, tmp_path, monkeypatch, capsys):
    """`hgca read --json` (what the Blender import reads): one object with the counts the sentence gives."""
    path = real_dir / "nuscenes_lidar_top_1532402927647951.pcd.bin"
    code, out, _ = run_cli(monkeypatch, capsys, "read", path, "-o", tmp_path / "n.npz", "--json")
    assert code == 0
    doc = json.loads(out.strip().splitlines()[-1])
    with np.load(tmp_path / "n.npz") as data:
        kept = len(data["points"])
        names = [k for k in data.files if k not in ("points", "origins", "offset")]
    assert doc["points"] == kept and doc["scans"] == 1 and doc["attributes"] == names
    assert set(doc["dropped"]) == {EGO_RETURNS} and kept + doc["dropped"][EGO_RETURNS] == expected_count(path)
    code, out, _ = run_cli(monkeypatch, capsys, "read", real_dir / "simple.las", "-o", tmp_path / "l.npz", "--json")
    assert code == 0 and json.loads(out.strip().splitlines()[-1])["dropped"] == {}

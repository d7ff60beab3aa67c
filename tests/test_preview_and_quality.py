"""The preview stage (a smooth surface of the coarse cells, scikit-image's marching cubes) and the quality levels
(which shipped weights a completion runs)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

import hgca_core
from hgca_core.config import QUALITY_FILES, CompletionConfig, DriveConfig
from hgca_core.errors import InputError
from hgca_core.meshing.voxel_mesh import smooth_cells_mesh, voxel_mesh

EXAMPLE = Path(hgca_core.__file__).parent / "examples"


def block(lo: int, hi: int, z: tuple[int, int] = (3, 8)) -> np.ndarray:
    return np.array([[x, y, k] for x in range(lo, hi) for y in range(lo, hi) for k in range(*z)])


def test_smooth_surface_closes_around_the_cells_it_stands_for() -> None:
    cells = block(5, 10)
    smooth, cubes = smooth_cells_mesh(cells, 0.2, (20, 20, 12)), voxel_mesh(cells, 0.2)
    assert smooth.is_watertight and smooth.volume > 0          # closed, normals outward
    assert abs(smooth.volume / cubes.volume - 1) < 0.3
    np.testing.assert_allclose(smooth.bounds.mean(axis=0), cubes.bounds.mean(axis=0), atol=1e-6)
    normals = np.abs(smooth.face_normals)
    assert (normals.max(axis=1) < 0.99).mean() > 0.3            # not cubes: many faces are slanted


def test_smooth_surface_keeps_thin_walls_and_drops_lone_cells() -> None:
    wall = np.array([[x, 6, z] for x in range(2, 18) for z in range(1, 10)])
    assert len(smooth_cells_mesh(wall, 0.2, (20, 20, 12)).faces) > 0
    assert len(smooth_cells_mesh(np.array([[4, 4, 4]]), 0.2, (20, 20, 12)).faces) == 0
    assert len(smooth_cells_mesh(np.zeros((0, 3), dtype=np.int64), 0.2, (20, 20, 12)).faces) == 0


def test_quality_picks_the_shipped_weights_and_named_files_win() -> None:
    best, fast = CompletionConfig(quality="best"), CompletionConfig(quality="fast")
    assert best.coarse_file() is None and best.fine_file() is None       # the loaders' default: the teacher
    assert Path(fast.coarse_file()).name == QUALITY_FILES["fast"][0]
    assert Path(fast.fine_file()).name == QUALITY_FILES["fast"][1]
    assert CompletionConfig(quality="fast", weights="mine.pt").coarse_file() == "mine.pt"
    assert DriveConfig().with_(quality="fast").completion.coarse_file() == fast.coarse_file()
    with pytest.raises(InputError, match="quality must be one of fast, best"):
        CompletionConfig(quality="fastest")


def test_cli_preview_writes_a_smooth_mesh(tmp_path: Path) -> None:
    out = tmp_path / "p.ply"
    subprocess.run([sys.executable, "-m", "hgca_core.cli", "complete", str(EXAMPLE / "street_scan0.laz"),
                    "--poses", str(EXAMPLE / "poses.json"), "--region", "30,0,1,9.6,9.6,6,0", "--stage", "preview",
                    "--t1", "3", "--progress", "none", "-o", str(out)], check=True, capture_output=True, timeout=300)
    mesh = trimesh.load(tmp_path / "p_s0.ply", process=False)
    assert len(mesh.faces) > 1000
    assert (np.abs(mesh.face_normals).max(axis=1) < 0.99).mean() > 0.2   # a surface, not the coarse stage's cubes


def test_complete_files_gives_the_clis_mesh_byte_for_byte(tmp_path: Path) -> None:
    """The README's Python example (`hgca_core.complete_files`) and `hgca complete` on the same scans: the same
    bytes, since the command is argv -> config -> this call (poses, sensor origins and region included)."""
    import hashlib

    scans = [str(EXAMPLE / f"street_scan{i}.laz") for i in (0, 1)]
    region = "30,0,1,9.6,9.6,6,0"
    subprocess.run([sys.executable, "-m", "hgca_core.cli", "complete", *scans, "--poses", str(EXAMPLE / "poses.json"),
                    "--region", region, "--stage", "coarse", "--t1", "4", "--samples", "2", "--progress", "none",
                    "-o", str(tmp_path / "cli.ply")], check=True, capture_output=True, timeout=300)
    paths = hgca_core.complete_files(scans, tmp_path / "lib.ply", poses=EXAMPLE / "poses.json", region=region,
                                     stage="coarse", t1=4, samples=2)
    assert [p.name for p in paths] == ["lib_s0.ply", "lib_s1.ply"]
    digest = lambda p: hashlib.sha256(p.read_bytes()).hexdigest()   # noqa: E731
    assert [digest(p) for p in paths] == [digest(tmp_path / f"cli_s{i}.ply") for i in (0, 1)]
    assert digest(paths[0]) != digest(paths[1])
    with pytest.raises(InputError, match="would overwrite an input"):
        hgca_core.complete_files(scans, tmp_path / "lib.ply", poses=tmp_path / "lib_s0.ply")

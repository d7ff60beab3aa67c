"""The shipped weights on the bundled example: a 12.8 x 12.8 m piece of the demo region, both stages.

These are the trained models a user gets, so the checks are about what they must do at the least: the
completion covers what the scanner saw (input points lie on or next to the output), stays in the region, and
adds geometry beyond the input (it completes, not just copies). Thresholds are loose on purpose; quality
numbers belong to `hgca eval` and the model card.
"""
import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

import hgca_core
from hgca_core.commands.demo import EXAMPLE_DIR
from hgca_core.io import read_scans
from hgca_core.io.poses import load_poses
from hgca_core.models.weights import shipped


@pytest.fixture(scope="module")
def example():
    poses = EXAMPLE_DIR / "poses.json"
    scans = read_scans([str(EXAMPLE_DIR / e.file) for e in load_poses(poses)], poses=str(poses))
    cx, cy, cz, sx, sy, sz, yaw = json.loads(poses.read_text())["region"]
    # a piece of the demo region beside the drive, at its full height
    region = hgca_core.Region.parse(f"{cx},{cy},{cz},12.8,12.8,{sz},{yaw}")   # poses.json: yaw in degrees
    local = region.to_local(scans.points)
    return scans.points[region.contains_local(local)], region


@pytest.mark.parametrize("stage,quality", [("coarse", "best"), ("full", "best"), ("coarse", "fast"),
                                           ("full", "fast")])
def test_shipped_weights_complete_the_example(example, stage, quality, one_thread):
    """Both quality levels: the teacher chains (best) and the few-step students (fast)."""
    from pathlib import Path

    from hgca_core.config import CompletionConfig

    cfg = CompletionConfig(stage=stage, quality=quality)
    for path in (cfg.coarse_file(), cfg.fine_file()) if stage == "full" else (cfg.coarse_file(),):
        assert Path(path or shipped("coarse")).exists(), "the package must ship its weights"
    assert shipped("coarse" if stage == "coarse" else "fine").exists(), "the package must ship its weights"
    pts, region = example
    res = hgca_core.complete(pts, region=region, config=cfg.with_(samples=1, seed=0))[0]
    v = res.vertices
    assert len(res.faces) > 1000
    local = region.to_local(v)
    assert np.all((local > -0.3) & (local < region.size + 0.3))
    # observed surface is reproduced: input points lie within about a cell of the output's vertices
    # (20 cm voxel faces: a point inside a cube is at most 0.17 m from a corner; the implicit mesh: 10 cm cells)
    d_in = cKDTree(v).query(pts[::7])[0]
    assert np.median(d_in) < (0.10 if stage == "full" else 0.20), np.median(d_in)
    # ... and completed: a good share of the output lies away from every input point
    assert np.mean(res.observed_distance > 0.3) > 0.05
    if stage == "full":
        # one surface: vertical rays through observed road points meet the mesh once within 15 cm of the point
        # (the earlier marching-cubes shell: twice, 5.8 cm apart), and the road faces up, towards the sensors
        from hgca_core.metrics.flatness import Patches, ray_samples

        local_pts = region.to_local(pts)
        road = local_pts[local_pts[:, 2] < np.quantile(local_pts[:, 2], 0.2)][::50]
        mesh = res.mesh.copy()
        mesh.vertices = local
        patches = Patches(road[:, :2] - 0.05, road[:, 2], size=0.1)
        _, hits, first = ray_samples(mesh, patches, spacing=0.1)
        assert np.mean(hits == 1) > 0.95, np.bincount(hits)
        tri = mesh.ray.intersects_first(np.c_[road[:, :2], road[:, 2] + 0.3], np.tile([0.0, 0.0, -1.0], (len(road), 1)))
        up = mesh.face_normals[tri[tri >= 0], 2]
        assert np.mean(up > 0.5) > 0.95


def test_results_about_the_shipped_weights_name_their_current_digests():
    """The evaluation on the weights record and the real-scan page name the shipped files by sha256: a file
    changed without them (new tensors, or a rewritten record) would leave the pages describing another file."""
    from pathlib import Path

    from hgca_core.io.digest import file_digest

    root = Path(__file__).resolve().parents[1]
    ev = json.loads((root / "hgca_core/weights/eval_test.json").read_text())
    assert ev["weights_sha256"] == {r: file_digest(root / p) for r, p in ev["weights"].items()}
    real = json.loads((root / "benchmarks/results/real_scans.json").read_text())["config"]
    assert real["weights_sha256"] == {r: file_digest(root / p) for r, p in real["weights"].items()}
    assert all(not Path(p).is_absolute() for p in [*ev["weights"].values(), *real["weights"].values()])


def test_model_card_table_names_each_files_size_and_parameters():
    """The model card's table of files against the files: a retrained or rewritten file changes its row."""
    import re
    from pathlib import Path

    from hgca_core.models.weights import load_file

    root = Path(__file__).resolve().parents[1]
    card = (root / "MODEL_CARD.md").read_text()
    for path in sorted((root / "hgca_core/weights").glob("*.pt")):
        blob = load_file(path)
        dicts = [blob["state_dict"]] + ([blob["autoencoder"]["state_dict"]] if "autoencoder" in blob else [])
        params = sum(v.numel() for d in dicts for v in d.values())
        row = re.search(rf"^\| `{re.escape(path.name)}` \| [^|]+ \| ([\d,]+) \| ([\d.]+) MB \|", card, re.M)
        assert row, path.name
        assert int(row.group(1).replace(",", "")) == params, path.name
        assert row.group(2) == f"{path.stat().st_size / 1e6:.2f}", path.name


def test_weights_record_is_the_rendering_of_the_shipped_files(tmp_path):
    """hgca_core/weights/MODEL_CARD.md is what `training.card` renders from the files beside it today (the torch
    version line aside): a record rewritten inside a file, or a file replaced, without re-rendering fails here."""
    import shutil
    from pathlib import Path

    from hgca_core.training.card import write_model_card

    weights = Path(__file__).resolve().parents[1] / "hgca_core" / "weights"
    copy = tmp_path / "weights"
    shutil.copytree(weights, copy, ignore=shutil.ignore_patterns("MODEL_CARD.md", "__pycache__"))
    fresh = write_model_card(copy).read_text().splitlines()
    shipped = (weights / "MODEL_CARD.md").read_text().splitlines()
    assert [line for line in fresh if not line.startswith("Card written with torch")] == \
        [line for line in shipped if not line.startswith("Card written with torch")]

"""`hgca eval` end to end on one small simulated sample: the coarse rows and the fine stage's two rows
(10 cm voxels and the implicit mesh) from small untrained fine weights. Quality is not asserted; the table,
its rows and its files are."""
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from hgca_core.dataset.samples import save_sample
from hgca_core.synth.dataset import QUICK_QUALITY, make_sample


@pytest.fixture(scope="module")
def small_split(tmp_path_factory):
    root = tmp_path_factory.mktemp("evaldata")
    (root / "val").mkdir()
    # the sensor the shipped weights were trained with (the paper's), so the completion is a real one
    sample = make_sample(1_000_123, 2, size=(12.8, 12.8, 8.0), quality=QUICK_QUALITY, profile="waymo")
    save_sample(root / "val" / "sample_1000123.npz", sample)
    return root


@pytest.fixture(scope="module")
def small_fine(tmp_path_factory):
    """Small untrained fine weights, biased so that the fine chain keeps cells (occupancy logit + 1) and the decoded
    distance dips below the meshing level (distance logit - 1). Unbiased, an untrained chain dies at once and every
    fine row scores the empty-completion penalty, so comparisons between runs would hold whatever the code did."""
    from hgca_core.models.autoencoder import Autoencoder, AutoencoderConfig
    from hgca_core.models.cgca import CGCAConfig, CGCAKernel
    from hgca_core.training.export import save_weights

    torch.manual_seed(0)
    kernel, autoencoder = CGCAKernel(CGCAConfig(channels=(8, 8, 8, 8, 8), steps=2)), Autoencoder(AutoencoderConfig())
    with torch.no_grad():
        kernel.head[2].bias[0] = 1.0
        autoencoder.fc_out.bias.fill_(-1.0)
    path = tmp_path_factory.mktemp("fw") / "fine_small.pt"
    save_weights(path, kernel, {"stage": "test"}, autoencoder=autoencoder)
    return path


@pytest.mark.slow   # minutes on 2 cores: `make test-slow` (CI runs it)
def test_eval_full_stage_table(small_split, small_fine, tmp_path, capsys):
    out = tmp_path / "eval.json"
    cmd = [sys.executable, "-m", "hgca_core.cli", "eval", "--data", str(small_split), "--split", "val",
           "--stage", "full", "--methods", "input,hgca,hgca-full", "--fine-weights", str(small_fine),
           "--samples", "2", "--t1", "2", "--t2", "2", "--out", str(out)]
    png = tmp_path / "scene.png"
    res = subprocess.run(cmd + ["--render", str(png)], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    doc = json.loads(out.read_text())
    rows = doc["rows"]
    assert set(rows) == {"input", "hGCA coarse (planner)", "hGCA (10 cm voxels)", "hGCA (implicit)"}
    # the weights the model rows ran with, named by content: the shipped coarse.pt and the given fine weights
    from hgca_core.io.digest import file_digest
    from hgca_core.models.weights import shipped

    assert doc["weights"] == {"coarse": str(shipped("coarse")), "fine": str(small_fine)}
    assert doc["weights_sha256"] == {"coarse": file_digest(shipped("coarse")), "fine": file_digest(small_fine)}
    # the rendering: ground truth, input, then the three model rows' first completions, 4 panels a row
    from PIL import Image

    sheet = np.asarray(Image.open(png).convert("RGB"))
    assert sheet.shape == (22 + 2 * (420 + 22), 4 * 640, 3)
    panel = lambda i: sheet[22 + (i // 4) * 442 + 22:22 + (i // 4) * 442 + 442, (i % 4) * 640:(i % 4 + 1) * 640]
    for i in range(5):                     # each drawn panel holds a picture, the slots after them are blank
        assert (panel(i) < 200).any(axis=2).mean() > 0.01, i
    for i in range(5, 8):
        assert (panel(i) == 255).all(), i
    for name, r in rows.items():
        assert 0.0 <= r["iou"] <= 1.0 and np.isfinite(r["resim_min"]) and r["seconds_per_completion"] > 0, name
    assert rows["hGCA (10 cm voxels)"]["k"] == 2 and np.isfinite(rows["hGCA (10 cm voxels)"]["tmd"])
    for name in ("hGCA (10 cm voxels)", "hGCA (implicit)"):   # the fine chain is alive: no empty-scan penalty
        assert rows[name]["resim_avg"] < 2.0 and rows[name]["iou"] > 0.02
    # the implicit row's time includes the meshing the voxel row leaves out
    assert rows["hGCA (implicit)"]["seconds_per_completion"] > rows["hGCA (10 cm voxels)"]["seconds_per_completion"]
    table = out.with_suffix(".md").read_text()
    assert "hGCA (implicit)" in table and "10cm^3" in table
    # a later run of one method keeps the other rows of the earlier file, and refuses other samples
    from hgca_core.cli import main   # the quick runs below in this process: fresh ones cost ~3 s each

    again = tmp_path / "again.json"
    assert main(cmd[3:8] + ["--methods", "input", "--samples", "2", "--reuse", str(out), "--out", str(again)]) == 0
    doc2 = json.loads(again.read_text())
    rows2 = doc2["rows"]
    assert set(rows2) == set(rows) and "reused_from" not in rows2["input"]
    assert rows2["hGCA (implicit)"] == {**rows["hGCA (implicit)"], "reused_from": "eval.json"}
    # the reused rows keep the weights they ran, by role, once (the input row runs none)
    assert (doc2["weights"], doc2["weights_sha256"]) == (doc["weights"], doc["weights_sha256"])
    # rows run now with other coarse weights than the reused rows' are refused before any scene runs
    from hgca_core.models.weights import save_file
    from hgca_core.training.export import blend_files

    other = save_file(blend_files(shipped("coarse"), shipped("coarse"), 0.5), tmp_path / "other.pt")
    mixed = tmp_path / "mixed.json"
    capsys.readouterr()
    assert main([*cmd[3:cmd.index("--methods")], "--methods", "hgca", "--weights", str(other), "--samples", "2",
                 "--t1", "2", "--reuse", str(out), "--out", str(mixed)]) == 2
    err = capsys.readouterr().err
    assert "other coarse weights" in err and "eval.json" in err and "eval val" not in err and not mixed.exists(), err
    assert main(cmd[3:8] + ["--methods", "input", "--samples", "3", "--reuse", str(out)]) == 2
    assert "other samples" in capsys.readouterr().err
    # with hgca-full, the hgca row borrows that run's coarse cells; alone, it runs the coarse stage itself: same row
    alone = tmp_path / "alone.json"
    rest = cmd[cmd.index("--methods") + 2:cmd.index("--out")]
    assert main([*cmd[3:cmd.index("--methods")], "--methods", "hgca", *rest, "--out", str(alone)]) == 0
    row, shared = json.loads(alone.read_text())["rows"]["hGCA coarse (planner)"], rows["hGCA coarse (planner)"]
    assert shared["tmd"] > 0                                    # two different completions, not one repeated
    for key in ("iou", "resim_min", "resim_avg", "tmd", "street_cd_min"):
        assert row[key] == shared[key], key


def test_eval_scores_what_complete_ships(small_split):
    """The hgca row is the score of `hgca_core.complete`'s own mesh (world frame, moved back into the sample's
    region frame), and the input row meshes its cells as the coarse stage does (cube faces)."""
    import hgca_core
    from hgca_core.geometry.region import Region
    from hgca_core.geometry.voxel import voxelize
    from hgca_core.meshing.voxel_mesh import voxel_mesh
    from hgca_core.metrics.evaluate import evaluate_sample
    from hgca_core.config import CompletionConfig
    from hgca_core.metrics.synthetic import evaluate_methods, load_method_models
    from hgca_core.models.weights import shipped
    from hgca_core.dataset.samples import load_sample
    from hgca_core.synth.rays import input_rays

    path = small_split / "val" / "sample_1000123.npz"
    settings = CompletionConfig(samples=1, seed=3, t1=2, precision="fp32")
    got = evaluate_methods(path, ["input", "hgca"], load_method_models(["hgca"], None), settings)
    sample = load_sample(path)
    region = Region.from_tuple(sample["region"])
    rays, scan = input_rays(sample)       # every hit, beyond the region too, as a user's scan holds them
    assert len(rays) > len(sample["input_points"])
    world = region.to_world(rays)
    origins = region.to_world(np.asarray(sample["input_origins"], dtype=np.float64))   # eval gives each ray's origin
    shipped = hgca_core.complete(world, region=region, seed=3, t1=2, weights=shipped("coarse"), precision="fp32",
                                 stage="coarse",
                                 origins=origins, origin_index=scan)[0]
    mesh = shipped.mesh.copy()
    mesh.vertices = region.to_local(mesh.vertices)
    want = evaluate_sample(sample, [mesh], [shipped.coarse_cells])
    assert want["resim_min"] < 2.0 and want["iou"] > 0.5                 # a real completion, not the penalty
    for key in ("iou", "resim_min", "street_cd_min"):
        assert got["hgca"][0][key] == pytest.approx(want[key], rel=1e-9, abs=1e-12), key
    # the input row: the region's s^0 cells, meshed like the coarse output
    s0 = voxelize(sample["input_points"], 0.2, region.size)
    want_input = evaluate_sample(sample, [voxel_mesh(s0, 0.2)], [s0])
    for key in ("iou", "resim_min", "street_cd_min"):
        assert got["input"][0][key] == want_input[key], key


def test_eval_render_wants_a_png(small_split, tmp_path):
    cmd = [sys.executable, "-m", "hgca_core.cli", "eval", "--data", str(small_split), "--split", "val",
           "--methods", "input", "--render", str(tmp_path / "scene.jpg")]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert res.returncode == 2 and "scene.jpg" in res.stderr and "PNG" in res.stderr
    assert not (tmp_path / "scene.jpg").exists()


def test_eval_full_stage_without_fine_weights_is_a_clear_error(small_split, tmp_path):
    cmd = [sys.executable, "-m", "hgca_core.cli", "eval", "--data", str(small_split), "--split", "val",
           "--stage", "full", "--methods", "hgca-full", "--fine-weights", str(tmp_path / "none.pt")]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert res.returncode == 2 and "none.pt" in res.stderr and "Traceback" not in res.stderr


def test_eval_weights_flags_choose_the_model_files():
    """--weights / --noplanner-weights put the named files in the hgca / gca rows (a run's checkpoint scored
    against the shipped model); unnamed, the shipped ones."""
    from hgca_core.metrics.synthetic import load_method_models
    from hgca_core.models.weights import shipped

    swapped = load_method_models(["gca", "hgca"], None, weights=str(shipped("coarse-noplanner")),
                                 noplanner_weights=str(shipped("coarse")))
    assert not swapped["hgca"].coarse.cfg.use_planner and swapped["gca"].coarse.cfg.use_planner
    default = load_method_models(["gca", "hgca"], None)
    assert default["hgca"].coarse.cfg.use_planner and not default["gca"].coarse.cfg.use_planner


def test_gallery_places_each_panel_under_its_caption(tmp_path):
    from PIL import Image

    from hgca_core.render import gallery

    red, blue = np.zeros((30, 40, 3), np.uint8), np.zeros((30, 40, 3), np.uint8)
    red[..., 0], blue[..., 2] = 255, 255
    gallery([("a", red), ("b", blue), ("c", red)], tmp_path / "g.png", columns=2, title="t")
    sheet = np.asarray(Image.open(tmp_path / "g.png").convert("RGB"))
    assert sheet.shape == (22 + 2 * (30 + 22), 80, 3)
    assert (sheet[44:74, :40] == [255, 0, 0]).all() and (sheet[44:74, 40:] == [0, 0, 255]).all()
    assert (sheet[96:126, :40] == [255, 0, 0]).all() and (sheet[96:126, 40:] == 255).all()
    with pytest.raises(ValueError, match="size"):
        gallery([("a", red), ("b", blue[:20])], tmp_path / "h.png")

"""`hgca eval` end to end on one small simulated sample: the coarse rows and the fine stage's two rows
(10 cm voxels and the implicit mesh) from small untrained fine weights. Quality is not asserted; the table,
its rows and its files are."""
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from hgca_core.synth.dataset import QUICK_QUALITY, make_sample, save_sample


@pytest.fixture(scope="module")
def small_split(tmp_path_factory):
    root = tmp_path_factory.mktemp("evaldata")
    (root / "val").mkdir()
    sample = make_sample(1_000_123, 2, size=(12.8, 12.8, 8.0), quality=QUICK_QUALITY)
    save_sample(root / "val" / "sample_1000123.npz", sample)
    return root


@pytest.fixture(scope="module")
def small_fine(tmp_path_factory):
    from hgca_core.models.autoencoder import Autoencoder, AutoencoderConfig
    from hgca_core.models.cgca import CGCAConfig, CGCAKernel
    from hgca_core.models.weights import save_weights

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("fw") / "fine_small.pt"
    save_weights(path, CGCAKernel(CGCAConfig(channels=(8, 8, 8, 8, 8), steps=2)), {"stage": "test"},
                 autoencoder=Autoencoder(AutoencoderConfig()))
    return path


def test_eval_full_stage_table(small_split, small_fine, tmp_path):
    out = tmp_path / "eval.json"
    cmd = [sys.executable, "-m", "hgca_core.cli", "eval", "--data", str(small_split), "--split", "val",
           "--stage", "full", "--methods", "input,hgca,hgca-full", "--fine-weights", str(small_fine),
           "--samples", "2", "--t1", "2", "--t2", "2", "--out", str(out)]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    rows = json.loads(out.read_text())["rows"]
    assert set(rows) == {"input", "hGCA coarse (planner)", "hGCA (10 cm voxels)", "hGCA (implicit)"}
    for name, r in rows.items():
        assert 0.0 <= r["iou"] <= 1.0 and np.isfinite(r["resim_min"]) and r["seconds_per_completion"] > 0, name
    assert rows["hGCA (10 cm voxels)"]["k"] == 2 and np.isfinite(rows["hGCA (10 cm voxels)"]["tmd"])
    # the implicit row's time includes the meshing the voxel row leaves out
    assert rows["hGCA (implicit)"]["seconds_per_completion"] > rows["hGCA (10 cm voxels)"]["seconds_per_completion"]
    table = out.with_suffix(".md").read_text()
    assert "hGCA (implicit)" in table and "10cm^3" in table
    # a later run of one method keeps the other rows of the earlier file, and refuses other samples
    again = tmp_path / "again.json"
    res = subprocess.run(cmd[:8] + ["--methods", "input", "--samples", "2", "--reuse", str(out), "--out", str(again)],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    rows2 = json.loads(again.read_text())["rows"]
    assert set(rows2) == set(rows) and "reused_from" not in rows2["input"]
    assert rows2["hGCA (implicit)"] == {**rows["hGCA (implicit)"], "reused_from": "eval.json"}
    bad = subprocess.run(cmd[:8] + ["--methods", "input", "--samples", "3", "--reuse", str(out)],
                         capture_output=True, text=True, timeout=600)
    assert bad.returncode == 2 and "other samples" in bad.stderr
    # hgca and hgca-full share their coarse chains in one process; alone, hgca-full runs them itself, same result
    alone = tmp_path / "alone.json"
    res = subprocess.run([*cmd[:cmd.index("--methods")], "--methods", "hgca-full",
                          *cmd[cmd.index("--methods") + 2:cmd.index("--out")], "--out", str(alone)],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    rows3 = json.loads(alone.read_text())["rows"]
    for name in ("hGCA (10 cm voxels)", "hGCA (implicit)"):
        for key in ("iou", "resim_min", "resim_avg", "tmd"):
            assert rows3[name][key] == rows[name][key], (name, key)


def test_eval_full_stage_without_fine_weights_is_a_clear_error(small_split, tmp_path):
    cmd = [sys.executable, "-m", "hgca_core.cli", "eval", "--data", str(small_split), "--split", "val",
           "--stage", "full", "--methods", "hgca-full", "--fine-weights", str(tmp_path / "none.pt")]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert res.returncode == 2 and "none.pt" in res.stderr and "Traceback" not in res.stderr

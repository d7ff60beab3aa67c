"""The prepared GPU check (`benchmarks/gpu_check.py`) runs on the CPU in its quick form, so it cannot rot before
a GPU is lent: it times coarse and full completion and training, compares the device's mesh with the CPU's
(on the CPU the two are the same run: identical cells, zero distance) and writes its page."""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

import hgca_core
from hgca_testdata import tiny_sample

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "gpu_check.py"


def test_gpu_check_runs_on_the_cpu_and_writes_its_page(tiny_dataset, tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    s = tiny_sample(3)
    pts = s["input_points"].astype(np.float64)
    np.savez(data / "inputs.npz", points=pts, origins=np.array([[3.0, 3.0, 2.0]]),
             origin_index=np.zeros(len(pts), dtype=np.int64), region=np.array([3.0, 3.0, 1.0, 6.0, 6.0, 4.0, 0.0]))
    shutil.copytree(tiny_dataset, data / "train_data")
    out = tmp_path / "results"
    env = {**os.environ, "PYTHONPATH": str(Path(hgca_core.__file__).parents[1])}
    res = subprocess.run([sys.executable, str(SCRIPT), "--device", "cpu", "--quick", "--data", str(data), "--out",
                          str(out)], capture_output=True, text=True, env=env, cwd=tmp_path, timeout=900)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    doc = json.loads((out / "gpu.json").read_text())
    assert doc["errors"] == {}
    parts = doc["parts"]
    for stage in ("coarse", "full"):
        assert parts[f"complete_{stage}"]["median_s"] > 0 and "coarse" in parts[f"complete_{stage}"]["stages_s"]
    check = parts["mesh_check"]
    assert check["device_vs_cpu"]["cell_iou"] == 1.0                  # on the CPU both runs are the same run
    assert check["device_vs_cpu"]["distance_m"]["max"] in (0.0, None)
    assert check["cpu_seed_vs_seed_plus_1"]["cell_iou"] < 1.0         # another seed: another sample
    assert parts["train_coarse"]["step_s"] > 0 and parts["train_coarse"]["steps_averaged"] == "1-10"
    page = (out / "gpu.md").read_text()
    assert "| coarse |" in page and "| full |" in page and "s a step" in page and (out / "gpu.png").is_file()


def test_gpu_check_without_its_inputs_says_how_to_make_them(tmp_path):
    res = subprocess.run([sys.executable, str(SCRIPT), "--device", "cpu", "--data", str(tmp_path / "none")],
                         capture_output=True, text=True, cwd=tmp_path, timeout=300,
                         env={**os.environ, "PYTHONPATH": str(Path(hgca_core.__file__).parents[1])})
    assert res.returncode == 2 and res.stderr.strip().splitlines()[-1].startswith("gpu_check: error: ")
    assert "--prepare" in res.stderr

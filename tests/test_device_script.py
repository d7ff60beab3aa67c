"""scripts/device_train.sh, the one prepared call that trains on a lent GPU, runs its whole path here on the CPU
(DEVICE=cpu): packed data in, trained weights with their record, the curve and the history out. A script that
broke with the CLI would otherwise be found only on the GPU machine, whose minutes are few."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hgca_core.io.digest import file_digest
from hgca_core.cli import main
from hgca_core.models.weights import WEIGHTS_DIR, load_file

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "device_train.sh"
# what the GPU machine's image lacks (the device tool's KINDS.md): training must not import any of them
ABSENT_THERE = ("trimesh", "embreex", "rtree", "fast_simplification", "pykdtree", "laspy", "lazrs", "plyfile",
                "open3d", "pyarrow", "bpy", "ray")


def run_script(env: dict, tmp_path: Path) -> subprocess.CompletedProcess:
    """The script with the packages the GPU machine lacks made unimportable (a sitecustomize that blocks them)."""
    site = tmp_path / "site"
    site.mkdir(exist_ok=True)
    (site / "sitecustomize.py").write_text(f"import sys\nfor m in {ABSENT_THERE!r}:\n    sys.modules[m] = None\n")
    skip = ("DATA", "OUT", "RUN", "MINUTES", "PACKED", "STASH")
    base = {k: v for k, v in os.environ.items() if not k.startswith(skip)}
    return subprocess.run(["bash", str(SCRIPT)], env={**base, "PY": sys.executable, "DEVICE": "cpu",
                                                       "RUN": str(tmp_path / "run"), "OMP_NUM_THREADS": "1",
                                                       "PYTHONPATH": str(site), **env},
                          capture_output=True, text=True, timeout=600)


def test_device_script_trains_on_packed_data_and_returns_the_weights(tiny_dataset, tmp_path):
    packed = tmp_path / "gpu_data" / "tiny"
    assert main(["synth", "--pack", str(tiny_dataset), "--out", str(packed)]) == 0
    out = tmp_path / "out"
    r = run_script({"DATA": str(packed), "OUT": str(out), "MINUTES": "0.05", "BATCH": "2",
                    "FROZEN": "1", "CUT_FREE": "1", "DISTILL": "0.5", "ABOVE": "1",
                    "TEACHER": str(WEIGHTS_DIR / "coarse.pt")}, tmp_path)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert {p.name for p in out.iterdir()} == {"coarse_gpu.pt", "coarse_gpu.history.json", "curves.png",
                                               "device_train.log"}
    meta = load_file(out / "coarse_gpu.pt")["meta"]
    assert meta["steps"] > 0 and str(packed) in meta["data"]
    history = json.loads((out / "coarse_gpu.history.json").read_text())
    assert history["step"] == meta["steps"] and history["sessions"][-1]["device"] == "cpu"
    recipe = history["sessions"][-1]["recipe"]
    assert recipe["free_weight"] == 8.0 and recipe["frozen_bn"] is True and recipe["cut_free_loss"] is True
    assert recipe["distill"] == 0.5 and recipe["distill_above"] is True and recipe["teacher"] == str(WEIGHTS_DIR / "coarse.pt")
    assert recipe["teacher_sha256"] == file_digest(WEIGHTS_DIR / "coarse.pt")
    assert any(h["kind"] == "val" for h in history["history"])
    assert "[coarse_gpu] " in (out / "device_train.log").read_text()


def test_device_script_trains_variants_side_by_side_each_with_its_own_settings(tiny_dataset, tmp_path):
    """Runs in one call share the GPU; a variant's settings must reach its run alone, and the files that come back
    stay within the device tool's 8."""
    packed = tmp_path / "gpu_data" / "tiny"
    assert main(["synth", "--pack", str(tiny_dataset), "--out", str(packed)]) == 0
    out = tmp_path / "out"
    r = run_script({"DATA": str(packed), "OUT": str(out), "MINUTES": "0.05", "BATCH": "2", "CUT_FREE": "1",
                    "VARIANTS": "d:DISTILL=0.5,ABOVE=1,LR=3e-4,BATCH=3 plain"}, tmp_path)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert {p.name for p in out.iterdir()} == {"d.pt", "d.history.json", "plain.pt", "plain.history.json",
                                               "curves.png", "device_train.log"}
    sd = json.loads((out / "d.history.json").read_text())["sessions"][-1]
    sp = json.loads((out / "plain.history.json").read_text())["sessions"][-1]
    rd, rp = sd["recipe"], sp["recipe"]
    assert rd["distill"] == 0.5 and rd["distill_above"] is True and sd["lr"] == 3e-4
    assert rp["distill"] == 0 and rp["distill_above"] is False and sp["lr"] == 1.5e-4
    assert sd["batch"] == 3 and sp["batch"] == 2
    assert rd["cut_free_loss"] is True and rp["cut_free_loss"] is True  # the shared setting reaches both
    assert load_file(out / "d.pt")["meta"]["steps"] > 0 and load_file(out / "plain.pt")["meta"]["steps"] > 0


@pytest.mark.parametrize("variants, says", [("a b c d", "at most 3"), ("a:DISTIL=1", "'DISTIL=1' in variant 'a'"),
                                            ("a a", "repeated"), ("a/b", "not made of")])
def test_device_script_refuses_variants_it_cannot_run_or_return(variants, says, tmp_path):
    packed = tmp_path / "gpu_data" / "empty"
    packed.mkdir(parents=True)
    r = run_script({"DATA": str(packed), "OUT": str(tmp_path / "out"), "VARIANTS": variants}, tmp_path)
    assert r.returncode == 2 and says in r.stderr, r.stderr
    assert not (tmp_path / "out").exists()


def test_device_script_without_packed_data_says_so(tmp_path):
    r = run_script({"DATA": " ", "OUT": str(tmp_path / "out")}, tmp_path)
    assert r.returncode == 2 and "no packed data" in r.stderr


def test_device_script_sets_a_batch_aside_and_trains_on_both_batches_the_val_one_first(tiny_dataset, tmp_path):
    """Two calls on the warm machine: the first moves its carried folders aside (STASH_ONLY=1), the second carries
    the next batch and, with DATA left out, trains on every folder of both, validating on a folder with a val
    split, whichever batch holds it."""
    import shutil

    first, second, stash = tmp_path / "batch1", tmp_path / "batch2", tmp_path / "stash"
    assert main(["synth", "--pack", str(tiny_dataset), "--out", str(first / "tiny")]) == 0
    env = {"PACKED": str(first), "STASH": str(stash), "OUT": str(tmp_path / "out1"), "STASH_ONLY": "1"}
    r = run_script(env, tmp_path)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert sorted(p.name for p in (stash / "tiny").rglob("*")) == sorted(p.name for p in (first / "tiny").rglob("*"))
    again = run_script(env, tmp_path)                     # the same folder name twice would mix two batches
    assert again.returncode == 2 and "exists already" in again.stderr
    (second / "a_train_only").mkdir(parents=True)         # sorts first, but holds no val split
    shutil.copytree(first / "tiny" / "train", second / "a_train_only" / "train")
    out = tmp_path / "out2"
    r = run_script({"PACKED": str(second), "STASH": str(stash), "OUT": str(out), "MINUTES": "0.05", "BATCH": "2"},
                   tmp_path)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    data = load_file(out / "coarse_gpu.pt")["meta"]["data"]
    assert data.index(str(stash / "tiny")) < data.index(str(second / "a_train_only")), data


def test_device_script_resume_continues_each_run_with_its_own_recipe(tiny_dataset, tmp_path):
    """A later call on the warm machine (RESUME=1) trains each variant's run on from its checkpoint, with the recipe
    the run started with, saying so of a setting the call names; a name without a run is refused, not restarted."""
    packed = tmp_path / "gpu_data" / "tiny"
    assert main(["synth", "--pack", str(tiny_dataset), "--out", str(packed)]) == 0
    first = run_script({"DATA": str(packed), "OUT": str(tmp_path / "o1"), "MINUTES": "0.05", "BATCH": "2",
                        "VARIANTS": "a:TURN=0.5,CUT_FREE=1,LR=3e-4"}, tmp_path)
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    steps = json.loads((tmp_path / "o1" / "a.history.json").read_text())["step"]
    out = tmp_path / "o2"
    r = run_script({"DATA": str(packed), "OUT": str(out), "MINUTES": "0.05", "BATCH": "2", "VARIANTS": "a:TURN=0",
                    "RESUME": "1"}, tmp_path)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "[a] RESUME=1 keeps the run's recipe: TURN=0 ignored" in r.stdout + r.stderr   # said, not silently dropped
    history = json.loads((out / "a.history.json").read_text())
    assert len(history["sessions"]) == 2 and history["step"] > steps
    last = history["sessions"][-1]
    assert last["recipe"]["turn_share"] == 0.5 and last["recipe"]["cut_free_loss"] is True and last["lr"] == 3e-4
    assert load_file(out / "a.pt")["meta"]["steps"] == history["step"]
    missing = run_script({"DATA": str(packed), "OUT": str(tmp_path / "o3"), "MINUTES": "0.05", "VARIANTS": "b",
                          "RESUME": "1"}, tmp_path)
    assert missing.returncode == 2 and "RESUME=1 but no" in missing.stderr + missing.stdout


def test_device_script_trains_seeds_of_one_recipe_side_by_side(tiny_dataset, tmp_path):
    """VARIANTS="s0:SEED=0 s1:SEED=1": runs that differ only in `hgca train --seed`, each recorded in its weights,
    so a lent GPU can give the spread between runs of one recipe (benchmarks/run_spread.py)."""
    packed = tmp_path / "gpu_data" / "tiny"
    assert main(["synth", "--pack", str(tiny_dataset), "--out", str(packed)]) == 0
    out = tmp_path / "o"
    r = run_script({"DATA": str(packed), "OUT": str(out), "MINUTES": "0.05", "BATCH": "2",
                    "VARIANTS": "s0:SEED=0 s1:SEED=1"}, tmp_path)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    metas = {n: load_file(out / f"{n}.pt")["meta"] for n in ("s0", "s1")}
    assert (metas["s0"]["seed"], metas["s1"]["seed"]) == (0, 1)

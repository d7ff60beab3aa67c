"""Training recipes as named configs: the shipped recipe reproduces the run of the flags it replaced bit for bit,
`--set` is typed and checked, and a resume continues the recipe saved in the checkpoint."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from hgca_core.cli import main
from hgca_core.models.weights import load_file, shipped
from hgca_core.training.recipes import RECIPES, parse_sets, resolve
from hgca_testdata import tiny_sample, with_distance_pairs

REFERENCE = Path(__file__).with_name("data") / "recipe_reference.json"
SMALL = ["--set", "channels=8,8,16,16,16", "--set", "crop=16", "--set", "buffer=2", "--threads", "1",
         "--no-progress"]


def make_dataset(root: Path) -> Path:
    """The tests' tiny dataset (conftest's `tiny_dataset`) in `root`, with the distance pairs the autoencoder and
    the fine stage need."""
    for split, seeds in (("train", range(3)), ("val", range(100, 102))):
        (root / split).mkdir(parents=True)
        for s in seeds:
            np.savez(root / split / f"sample_{s:07d}.npz", **with_distance_pairs(tiny_sample(s)))
    return root


def tensors_sha256(sd: dict[str, torch.Tensor]) -> str:
    """One digest of a state dict: names, dtypes, shapes and bytes, in name order."""
    h = hashlib.sha256()
    for k in sorted(sd):
        v = sd[k].detach().cpu().contiguous()
        h.update(f"{k}|{v.dtype}|{tuple(v.shape)}|".encode())
        h.update(v.reshape(-1).view(torch.uint8).numpy().tobytes() if v.numel() else b"")
    return h.hexdigest()


def run_digest(out: Path, export: Path) -> dict:
    """What a short run leaves, as digests: weights, their average, the exported file's tensors, the logs."""
    ck = load_file(out / "ckpt.pt")
    logs = [{k: v for k, v in h.items() if k not in ("elapsed_s", "step_s")} for h in ck["state"]["history"]]
    return {"model_sha256": tensors_sha256(ck["model"]), "ema_sha256": tensors_sha256(ck["ema"]["model"]),
            "export_sha256": tensors_sha256(torch.load(export, weights_only=True)["state_dict"]), "logs": logs}


def cpu_kind() -> str:
    """What decides how a CPU rounds bf16 GEMMs: its name alone is not enough (a VM's generic name covers Ice Lake
    and Sapphire Rapids alike), so torch's kernel level and the instruction sets that change the GEMM path too."""
    from hgca_core.hardware import cpu_name
    flags: set[str] = set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                flags = set(line.split(":", 1)[1].split())
                break
    except OSError:
        pass
    isa = sorted(f for f in flags if f in {"avx2", "avx512f", "avx512_vnni", "avx512_bf16", "avx512_fp16",
                                          "amx_tile", "amx_bf16", "amx_int8", "avx_vnni"})
    return f"{cpu_name()} | {torch.backends.cpu.get_cpu_capability()} | {' '.join(isa)}"


SHIPPED = ("coarse-shipped", "coarse-noplanner-shipped", "fine-shipped", "autoencoder")


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_recipe_reproduces_the_flags_it_replaced_bit_for_bit(name, tmp_path, one_thread):
    """`hgca train --recipe NAME` against the run of the old flags (`recipe_reference.json`, measured by
    data/make_recipe_reference.py with the training code before recipes): the first 50 steps' weights, their
    average, the logs and the export (coarse-shipped's blended with the shipped weights), identical."""
    from hgca_core.io.digest import file_digest

    ref = json.loads(REFERENCE.read_text())
    for stage, digest in ref["weights_sha256"].items():
        assert file_digest(shipped(stage.replace("_", "-"))) == digest, \
            f"the shipped {stage}.pt changed since the reference was measured: run data/make_recipe_reference.py"
    if cpu_kind() != ref["cpu"]:
        pytest.skip(f"bf16 GEMMs round by CPU kind: the reference was measured on {ref['cpu']}, this is {cpu_kind()}")
    data = make_dataset(tmp_path / "data")
    out, export = tmp_path / "run", tmp_path / "w.pt"
    # a budget, not the recipe: no validation but the last, whatever the machine's load
    assert main(["train", "--recipe", name, "--data", str(data), "--out", str(out), "--max-steps", str(ref["steps"]),
                 "--minutes", "60", "--set", "val_every=1000", "--threads", "1", "--no-progress",
                 "--export", str(export)]) == 0
    got = run_digest(out, export)
    assert got == {k: ref["runs"][name][k] for k in got}


def test_shipped_recipe_is_the_one_the_shipped_coarse_weights_record():
    """The table's coarse-shipped entry against the metadata of hgca_core/weights/coarse.pt: its last fine-tune's
    session record and its blend."""
    blob = torch.load(shipped("coarse"), weights_only=True)
    meta = blob["meta"]
    session = meta["blend"]["b"]["sessions"][-1]
    r = RECIPES["coarse-shipped"]
    rec = session["recipe"]
    assert (r.crop, r.focus, r.free_weight, r.cut, r.cut_free_loss, r.turn, r.distill) == (
        rec["crop"], rec["focus_share"], rec["free_weight"], rec["cut_share"], rec["cut_free_loss"],
        rec["turn_share"], rec["distill"])
    assert (r.lr, r.batch, r.precision, r.blend) == (session["lr"], session["batch"], session["precision"],
                                                    meta["blend"]["t"])
    assert rec["teacher_sha256"] == meta["blend"]["b"]["init"]["sha256"] == meta["blend"]["a"]["sha256"]
    assert r.init_from == str(shipped("coarse")) and r.free_space is blob["config"]["free_space"] is True


@pytest.mark.parametrize("stage", ["coarse-noplanner", "fine"])
def test_the_other_shipped_recipes_are_the_ones_their_weights_record(stage):
    """Their runs recorded precision, batch-free sessions (2 chains, the default then), the crop and focus, and a
    start from the stage's previous weights with the free space switched on."""
    blob = torch.load(shipped(stage), weights_only=True)
    r = RECIPES[f"{stage}-shipped"]
    sessions = blob["meta"]["sessions"]
    assert {s["precision"] for s in sessions} == {r.precision} and all("batch" not in s for s in sessions)
    assert r.batch == 2 and r.free_space is blob["config"]["free_space"] is True and r.init_from == str(shipped(stage))
    assert any("initialised from the previous" in n for n in blob["meta"]["notes"])
    if stage == "fine":
        assert r.crop == blob["config"]["crop"]
    else:
        assert {(s["recipe"]["crop"], s["recipe"]["focus_share"]) for s in sessions} == {(r.crop, r.focus)}


def test_set_is_typed_checked_and_refuses_unknown_keys():
    assert parse_sets(["lr=1e-4", "batch=3", "free_space=true", "channels=8,16", "blend=none"]) == {
        "lr": 1e-4, "batch": 3, "free_space": True, "channels": (8, 16), "blend": None}
    assert resolve("coarse", parse_sets(["lr=1e-4"])).lr == 1e-4 and RECIPES["coarse"].lr == 5e-4   # frozen table
    from hgca_core.errors import InputError

    for item, says in (("nosuch=1", "no such recipe field"), ("batch=2.5", "whole number"), ("lr=nan", "finite"),
                       ("free_space=maybe", "true or false"), ("stage=fine", "recipe names the stage"),
                       ("lr", "key=value")):
        with pytest.raises(InputError, match=says):
            parse_sets([item])
    with pytest.raises(InputError, match="given twice"):
        parse_sets(["lr=1e-4", "lr=2e-4"])


def test_resume_continues_the_saved_recipe_and_says_what_changes(tiny_dataset, tmp_path, capsys, one_thread):
    out = tmp_path / "run"
    base = ["train", "--data", str(tiny_dataset), "--out", str(out), *SMALL]
    assert main(base + ["--recipe", "coarse-noplanner", "--set", "lr=2e-4", "--set", "focus=0.25",
                        "--max-steps", "1"]) == 0
    saved = load_file(out / "ckpt.pt")["recipe"]
    assert saved["name"] == "coarse-noplanner" and saved["fields"]["lr"] == 2e-4 and saved["fields"]["crop"] == 16
    # a resume without flags trains on with the saved recipe: nothing re-applied from defaults
    assert main(["train", "--data", str(tiny_dataset), "--out", str(out), "--threads", "1", "--no-progress",
                 "--resume", "--max-steps", "1"]) == 0
    ck = load_file(out / "ckpt.pt")
    assert ck["recipe"] == saved and [s["recipe"]["focus_share"] for s in ck["state"]["sessions"]] == [0.25, 0.25]
    assert ck["state"]["sessions"][-1]["lr"] == 2e-4
    capsys.readouterr()
    assert main(base + ["--resume", "--max-steps", "1", "--set", "lr=1e-4"]) == 0
    assert "lr 0.0001 (was 0.0002)" in capsys.readouterr().err
    assert load_file(out / "ckpt.pt")["recipe"]["fields"]["lr"] == 1e-4
    for extra, says in ((["--set", "free_space=true"], "keeps its free_space"),
                        (["--recipe", "coarse"], "trained with the recipe coarse-noplanner")):
        assert main(base + ["--resume", "--max-steps", "1"] + extra) == 2
        assert says in capsys.readouterr().err
    assert main(base + ["--max-steps", "1"]) == 2     # a new run over an existing one
    assert "--resume" in capsys.readouterr().err

import hashlib
import json
import os
import subprocess
import sys

import pytest
import torch

from hgca_core.cli import main
from hgca_core.models.gca import GCAConfig
from hgca_core.models.weights import load_coarse, load_file, trained_weights
from hgca_core.training.coarse import CoarseTask
from hgca_core.training.trainer import EMA, train

SMALL = dict(channels=(8, 8, 16, 16, 16))


def _task(data, planner=True):
    return CoarseTask(str(data), GCAConfig(use_planner=planner, steps=4, **SMALL), crop=24, val_count=1)


def assert_identical(a, b, where="checkpoint"):
    """Nested dicts / lists / tuples of tensors and plain values equal bit for bit."""
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b), where
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), f"{where}: keys {sorted(a)} != {sorted(b)}"
        for k in a:
            assert_identical(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            assert_identical(x, y, f"{where}[{i}]")
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


@pytest.fixture
def one_thread():
    """Bit-for-bit comparisons need one CPU thread: with several, index_add_/sum reductions may add in another
    order from run to run (the test failed about 1 run in 3 under a loaded 2-core machine)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def test_budgeted_training_checkpoints_and_resumes_exactly(tiny_dataset, tmp_path, one_thread):
    out = tmp_path / "run"
    s1 = train(_task(tiny_dataset), out, minutes=5, max_steps=3, batch=2, buffer_size=3, progress=False)
    assert s1["step"] == 3 and (out / "ckpt.pt").exists() and (out / "curve.png").exists()
    ck = load_file(out / "ckpt.pt")   # weights_only: the checkpoint holds tensors and plain values only
    assert ck["state"]["step"] == 3 and len(ck["ranks"]) == 1 and len(ck["ranks"][0]["buffer"]["chains"]) == 3
    ts = [c["t"] for c in ck["ranks"][0]["buffer"]["chains"]]
    assert max(ts) >= 1  # chains advanced by infusion steps
    assert ck["ema"]["n"] == 3
    assert any(not torch.equal(ck["ema"]["model"][k], ck["model"][k]) for k in ck["model"])  # an average, not a copy
    assert trained_weights(ck) is ck["ema"]["model"]
    s2 = train(_task(tiny_dataset), out, minutes=5, max_steps=2, resume=True, batch=2, buffer_size=3, progress=False)
    assert s2["step"] == 5 and len(s2["sessions"]) == 2
    hist = json.loads((out / "history.json").read_text())
    assert [h for h in hist if h["kind"] == "val"] and all(0.0 <= h["val_iou"] <= 1.0 for h in hist if h["kind"] == "val")
    # 3 steps + resume + 2 steps is the run of 5 straight steps: weights, optimiser, average, chains, streams
    straight = train(_task(tiny_dataset), tmp_path / "straight", minutes=5, max_steps=5, batch=2, buffer_size=3,
                     progress=False)
    assert straight["step"] == 5
    resumed, once = load_file(out / "ckpt.pt"), load_file(tmp_path / "straight" / "ckpt.pt")
    assert resumed["ema"]["n"] == 5  # the average resumes too
    for key in ("model", "optim", "ema", "ranks"):
        assert_identical(resumed[key], once[key], key)
    assert resumed["optim"]["state"][0]["step"] == 5
    model, meta = load_coarse(out / "ckpt.pt")     # a coarse checkpoint stands in for weights: its average
    assert meta["steps"] == 5 and all(torch.equal(v, resumed["ema"]["model"][f"model.{k}"])
                                      for k, v in model.state_dict().items())


def test_a_resumed_run_takes_a_new_learning_rate_and_records_it(tiny_dataset, tmp_path):
    """`--lr` on a resume replaces the checkpoint's rate from that step on (the run's notes and the session say
    so); without it the run keeps its own."""
    out = tmp_path / "run"
    train(_task(tiny_dataset), out, minutes=5, max_steps=2, batch=2, buffer_size=3, progress=False, lr=3e-4)
    s = train(_task(tiny_dataset), out, minutes=5, max_steps=1, resume=True, batch=2, buffer_size=3, progress=False)
    assert load_file(out / "ckpt.pt")["optim"]["param_groups"][0]["lr"] == 3e-4 and not s.get("notes")
    s = train(_task(tiny_dataset), out, minutes=5, max_steps=1, resume=True, batch=2, buffer_size=3, progress=False,
              lr=1e-4)
    assert load_file(out / "ckpt.pt")["optim"]["param_groups"][0]["lr"] == 1e-4
    assert s["notes"] == ["learning rate 0.0001 from step 3 on (was 0.0003)"]
    assert [ses["lr"] for ses in s["sessions"]] == [3e-4, 3e-4, 1e-4]


def test_run_record_names_the_device_used(tiny_dataset, tmp_path):
    from hgca_core.hardware import cpu_name

    s = train(_task(tiny_dataset, planner=False), tmp_path / "d", minutes=5, max_steps=1, batch=1, buffer_size=1,
              progress=False, device="cpu")
    ses = s["sessions"][-1]
    assert ses["device"] == "cpu" and ses["device_name"] == cpu_name() and ses["device_name"]
    assert ses["recipe"] == {"crop": _task(tiny_dataset, planner=False).crop, "focus_share": 0.0, "free_weight": 0.0,
                             "cut_share": 0.0, "cut_free_loss": False, "turn_share": 0.0,
                             "distill": 0.0, "teacher": None, "teacher_sha256": None}
    from hgca_core.errors import InputError

    with pytest.raises(InputError, match="--device must be cpu, cuda or cuda:N"):
        train(_task(tiny_dataset, planner=False), tmp_path / "e", minutes=5, max_steps=1, device="tpu")
    if not torch.cuda.is_available():
        with pytest.raises(InputError, match="sees no CUDA GPU"):
            train(_task(tiny_dataset, planner=False), tmp_path / "e", minutes=5, max_steps=1, device="cuda")


def test_loss_falls_when_overfitting_one_example(tiny_dataset, tmp_path):
    s = train(_task(tiny_dataset, planner=False), tmp_path / "o", minutes=5, max_steps=40, batch=1, buffer_size=1,
              lr=3e-3, progress=False, val_every_min=1e9)
    losses = [h["loss"] for h in s["history"] if h["kind"] == "train"]
    assert losses[-1] < 0.7 * losses[0]


@pytest.mark.slow   # minutes on 2 cores: `make test-slow` (CI runs it)
def test_torchrun_two_cpu_ranks_with_their_own_streams(tiny_dataset, tmp_path):
    """Two gloo ranks: each draws its own chains and keeps its own random streams, also across a resume."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port", "29533",
           "-m", "hgca_core.cli", "train", "--data", str(tiny_dataset), "--out", str(tmp_path / "ddp"),
           "--max-steps", "2", "--minutes", "5", "--set", "crop=24", "--set", "batch=1", "--set", "buffer=2",
           "--set", "channels=8,8,16,16,16", "--no-progress", "--device", "cpu"]
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    ck = load_file(tmp_path / "ddp" / "ckpt.pt")
    assert ck["state"]["step"] == 2 and ck["state"]["sessions"][0]["world_size"] == 2
    r0, r1 = ck["ranks"]
    assert not torch.equal(r0["rng"]["torch"], r1["rng"]["torch"])
    assert r0["buffer"]["rng"] != r1["buffer"]["rng"]
    assert [c["t"] for c in r1["buffer"]["chains"]] == [1, 1]   # batch 1, 2 chains, 2 steps
    res = subprocess.run([*cmd[:cmd.index("--max-steps") + 1], "1", *cmd[cmd.index("--max-steps") + 2:], "--resume"],
                         capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    again = load_file(tmp_path / "ddp" / "ckpt.pt")
    a0, a1 = again["ranks"]
    assert again["state"]["step"] == 3 and not torch.equal(a0["rng"]["torch"], a1["rng"]["torch"])
    for before, after in ((r0, a0), (r1, a1)):   # each rank went on with its own chains, not fresh ones
        assert sorted(c["t"] for c in after["buffer"]["chains"]) == [1, 2]
        assert torch.equal(after["buffer"]["chains"][1]["s0"], before["buffer"]["chains"][1]["s0"])


def test_ema_warms_up_then_averages():
    lin = torch.nn.Linear(1, 1, bias=False)
    with torch.no_grad():
        lin.weight.fill_(0.0)
    ema = EMA(lin, decay=0.9)
    with torch.no_grad():
        lin.weight.fill_(1.0)
    ema.update(lin)              # warm-up decay (1 + 0) / (10 + 0) = 0.1
    assert abs(float(ema.module.weight) - 0.9) < 1e-6
    for _ in range(200):
        ema.update(lin)
    assert abs(float(ema.module.weight) - 1.0) < 1e-6 and not ema.module.weight.requires_grad
    with torch.no_grad():
        lin.weight.fill_(0.0)
    ema.update(lin)              # decay capped at 0.9 once n is large
    assert abs(float(ema.module.weight) - 0.9) < 1e-6


def test_ema_averages_batchnorm_statistics_and_copies_the_batch_count():
    bn = torch.nn.BatchNorm1d(1)
    ema = EMA(bn, decay=0.9)
    for _ in range(100):
        ema.update(bn)                   # past the warm-up
    with torch.no_grad():
        bn.running_mean.fill_(1.0)
        bn.num_batches_tracked.fill_(7)
    ema.update(bn)
    assert abs(float(ema.module.running_mean) - 0.1) < 1e-6        # 0.9 * 0 + 0.1 * 1, not the live 1.0
    assert int(ema.module.num_batches_tracked) == 7


def test_every_checkpoint_accounts_for_its_steps_in_sessions(tiny_dataset, tmp_path, monkeypatch):
    """A checkpoint written mid-session lists that session so far (a run killed before its session ends, or a
    checkpoint copied and exported mid-run, keeps the record of every step it holds), and the last one lists
    each session once."""
    import hgca_core.training.trainer as trainer

    saved = []
    real_save = trainer.save_file

    def spy(obj, path):
        if "optim" in obj:   # ckpt.pt, not best.pt
            saved.append((obj["state"]["step"], [s["steps"] for s in obj["state"]["sessions"]]))
        return real_save(obj, path)

    monkeypatch.setattr(trainer, "save_file", spy)
    out = tmp_path / "run"
    train(_task(tiny_dataset), out, minutes=5, max_steps=4, batch=2, buffer_size=3, progress=False, ckpt_every_min=0)
    assert len(saved) >= 3   # periodic checkpoints after steps 1-3, then the session's last
    assert all(sum(steps) == step for step, steps in saved), saved
    assert saved[-1] == (4, [4])
    saved.clear()
    train(_task(tiny_dataset), out, minutes=5, max_steps=2, resume=True, batch=2, buffer_size=3, progress=False,
          ckpt_every_min=0)
    assert all(sum(steps) == step for step, steps in saved) and saved[-1] == (6, [4, 2]), saved


def test_sigterm_stops_after_the_step_with_a_checkpoint(tiny_dataset, tmp_path):
    import signal
    import time

    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "hgca_core.cli", "train", "--recipe", "coarse-noplanner", "--data", str(tiny_dataset),
           "--out", str(tmp_path / "sig"), "--minutes", "10", "--set", "crop=24", "--set", "channels=8,8,16,16,16",
           "--no-progress"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        for line in proc.stdout:               # the first log line comes after step 10
            if '"kind": "train"' in line:
                break
        proc.send_signal(signal.SIGTERM)
        t0 = time.time()
        out, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 0, err[-2000:]
    assert time.time() - t0 < 60 and "SIGTERM: stopping" in out
    ck = load_file(tmp_path / "sig" / "ckpt.pt")
    assert ck["state"]["step"] >= 10 and len(ck["state"]["sessions"]) == 1
    assert [h for h in ck["state"]["history"] if h["kind"] == "val"]   # validated on the way out


def test_signal_handlers_come_back_when_a_step_raises(tiny_dataset, tmp_path, monkeypatch):
    import signal

    import pytest

    from hgca_core.training.coarse import CoarseLoss

    def broken(self, chains):
        raise RuntimeError("step failed")

    monkeypatch.setattr(CoarseLoss, "forward", broken)
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    with pytest.raises(RuntimeError, match="step failed"):
        train(_task(tiny_dataset, planner=False), tmp_path / "b", minutes=5, max_steps=3, batch=1, buffer_size=1,
              progress=False)
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


def test_several_data_folders_train_on_the_union_and_validate_on_the_first(tiny_dataset, tmp_path, capsys,
                                                                           one_thread):
    """`--data A B`: B's train samples (built with `hgca synth --first`) join A's; val stays A's, so runs that add
    data are selected on the same scenes; a folder without a train split is an error, not silently skipped, except
    a first folder that holds the val split alone."""
    import shutil
    from pathlib import Path

    import numpy as np

    from hgca_core.dataset.samples import split_files
    from hgca_core.errors import InputError
    from hgca_testdata import tiny_sample

    more = tmp_path / "more"
    (more / "train").mkdir(parents=True)
    np.savez(more / "train" / "sample_0001000.npz", **tiny_sample(1000))
    both = [str(tiny_dataset), str(more)]
    train_files = split_files(both, "train")
    assert [p.name for p in train_files] == [f"sample_{s:07d}.npz" for s in (0, 1, 2, 1000)]
    assert split_files(both, "val") == split_files(tiny_dataset, "val")
    with pytest.raises(InputError, match="no samples in"):
        split_files([str(tiny_dataset), str(tmp_path / "empty")], "train")
    val_only = tmp_path / "val_only"                      # validation scenes packed apart from the training batches
    shutil.copytree(Path(tiny_dataset) / "val", val_only / "val")
    assert split_files([str(val_only), str(more)], "train") == split_files(str(more), "train")
    assert split_files([str(val_only), str(more)], "val") == sorted((val_only / "val").glob("sample_*.npz"))
    with pytest.raises(InputError, match="no samples in"):   # only the first folder, the validation one, may lack it
        split_files([str(more), str(val_only)], "train")
    with pytest.raises(InputError, match="no samples in"):
        split_files(str(val_only), "train")
    def run(out, data):   # the CLI in this process (its exit status and stderr)
        return main(["train", "--recipe", "coarse-noplanner", "--data", *data, "--out", str(out), "--max-steps", "1",
                     "--set", "batch=1", "--set", "buffer=1", "--set", "crop=24", "--set", "channels=8,8,16,16,16",
                     "--minutes", "5", "--no-progress"])

    assert run(tmp_path / "run", both) == 0
    ses = load_file(tmp_path / "run" / "ckpt.pt")["state"]["sessions"][-1]
    assert ses["train_folders"] == sorted(both) and "sample_0001000.npz" in ses["train_samples"]
    shutil.rmtree(more / "train")
    (more / "train").mkdir()
    capsys.readouterr()
    assert run(tmp_path / "bad", both) == 2
    assert str(more / "train") in capsys.readouterr().err


def test_export_blended_toward_the_weights_the_run_started_from(tiny_dataset, tmp_path, capsys, one_thread):
    """Recipe field `blend` T: the export writes (1 - T) * init_from + T * the run's EMA weights and says so in the
    meta (which the card renders); it needs init_from, and T lies strictly between 0 and 1 (exit 2, nothing
    written)."""
    from hgca_core.models.gca import GCAKernel
    from hgca_core.training.export import save_weights

    torch.manual_seed(3)
    a = save_weights(tmp_path / "a.pt", GCAKernel(GCAConfig(use_planner=False, **SMALL)), {"steps": 5})

    def run(*extra):   # in this process (the CLI's exit status and stderr): 5 fresh processes cost ~20 s
        return main(["train", "--recipe", "coarse-noplanner", "--data", str(tiny_dataset), "--out",
                     str(tmp_path / "r"), "--set", "batch=1", "--set", "buffer=1", "--set", "crop=24", "--no-progress",
                     *extra])

    assert run("--max-steps", "1", "--minutes", "5", "--set", f"init_from={a}", "--set", "blend=0.25") == 0
    assert run("--minutes", "0", "--export", str(tmp_path / "plain.pt"), "--set", "blend=none") == 0
    assert run("--minutes", "0", "--export", str(tmp_path / "mix.pt")) == 0
    mix, plain, base = (load_file(tmp_path / f) for f in ("mix.pt", "plain.pt", "a.pt"))
    k = next(n for n, v in plain["state_dict"].items() if v.is_floating_point() and v.abs().sum() > 0)
    want = (0.75 * base["state_dict"][k].float() + 0.25 * plain["state_dict"][k].float()).half()
    assert torch.equal(mix["state_dict"][k], want)
    # the run's part is its val selection (best.pt, here its one step's average), named with its digest and score
    b = mix["meta"]["blend"]["b"]
    assert mix["meta"]["blend"]["t"] == 0.25 and b["file"] == str(tmp_path / "r" / "best.pt")
    assert b["sessions"] == plain["meta"]["sessions"] and b["selected"] == plain["meta"]["selected"]
    assert b["sha256"] == hashlib.sha256((tmp_path / "r" / "best.pt").read_bytes()).hexdigest()
    capsys.readouterr()
    for bad in (["--set", "blend=2"], ["--set", "blend=0.5", "--set", "init_from=none"]):
        code = main(["train", "--recipe", "coarse-noplanner", "--data", str(tiny_dataset), "--out",
                     str(tmp_path / "x"), *bad])
        err = capsys.readouterr().err
        assert code == 2 and "blend" in err and not (tmp_path / "x").exists(), err

def test_the_best_validation_weights_are_kept_beside_the_last(tiny_dataset, tmp_path, monkeypatch):
    """best.pt holds the average of the step whose validation scored best (here the second of three), with the
    record up to that step, and loads as coarse weights; ckpt.pt still holds the last step."""
    task = _task(tiny_dataset)
    scores = iter([0.5, 0.7, 0.6])
    monkeypatch.setattr(task, "validate", lambda model: {"val_iou": next(scores)})
    out = tmp_path / "run"
    s = train(task, out, minutes=5, max_steps=3, batch=1, buffer_size=1, progress=False, val_every_min=0)
    assert [h["val_iou"] for h in s["history"] if h["kind"] == "val"] == [0.5, 0.7, 0.6]
    best, last = load_file(out / "best.pt"), load_file(out / "ckpt.pt")
    assert s["best_val"] == {"key": "val_iou", "value": 0.7, "step": 2} == best["state"]["best_val"]
    assert best["state"]["step"] == 2 and last["state"]["step"] == 3
    assert [ses["steps"] for ses in best["state"]["sessions"]] == [2]   # the session as far as the weights go
    assert best["ema"]["n"] == 2 and last["ema"]["n"] == 3
    assert any(not torch.equal(best["ema"]["model"][k], last["ema"]["model"][k]) for k in last["ema"]["model"])
    model, meta = load_coarse(out / "best.pt")
    assert meta["steps"] == 2 and all(torch.equal(v, best["ema"]["model"][f"model.{k}"])
                                      for k, v in model.state_dict().items())
    # a resumed session that never beats 0.7 leaves best.pt alone
    monkeypatch.setattr(task, "validate", lambda model: {"val_iou": 0.65})
    train(task, out, minutes=5, max_steps=1, resume=True, batch=1, buffer_size=1, progress=False)
    assert load_file(out / "best.pt")["state"]["step"] == 2


def test_the_seed_starts_a_new_runs_streams_and_a_resume_keeps_them(tiny_dataset, tmp_path, one_thread, capsys):
    """Runs of one recipe measure its spread only if they can differ: --seed starts a new run's streams (initial
    weights, crops, chains), the same seed gives the same run, the record and card keep it, and a resume that
    names another seed is refused (exit 2) instead of being ignored while the checkpoint's streams go on."""
    from hgca_core.training.card import _trained
    from hgca_core.training.trainer import run_record

    kw = dict(minutes=5, max_steps=2, batch=2, buffer_size=3, progress=False)
    train(_task(tiny_dataset), tmp_path / "a", **kw)
    train(_task(tiny_dataset), tmp_path / "b", seed=1, **kw)
    train(_task(tiny_dataset), tmp_path / "c", seed=1, **kw)
    a, b, c = (load_file(tmp_path / n / "ckpt.pt") for n in "abc")
    assert any(not torch.equal(a["model"][k], b["model"][k]) for k in a["model"])
    assert_identical(b["model"], c["model"])
    assert (a["state"]["seed"], b["state"]["seed"]) == (0, 1)
    assert run_record(b)["seed"] == 1 and _trained(run_record(b)).endswith(", seed 1")
    assert "seed" not in _trained(run_record(a))
    from hgca_core.errors import InputError
    from hgca_core.training.export import lineage

    with pytest.raises(InputError, match="seed must be 0 or more"):
        train(_task(tiny_dataset), tmp_path / "neg", seed=-1, **kw)
    assert not (tmp_path / "neg").exists()                                     # refused before the run folder
    assert lineage(tmp_path / "b" / "ckpt.pt", run_record(b))["seed"] == 1     # a blend or start keeps it

    cmd = ["train", "--data", str(tiny_dataset), "--out", str(tmp_path / "cli"), "--max-steps", "1", "--set",
           "buffer=3", "--set", "crop=24", "--set", "channels=8,8,16,16,16", "--minutes", "5", "--no-progress"]
    assert main([*cmd, "--seed", "1"]) == 0     # the CLI in this process: three fresh ones cost ~15 s
    capsys.readouterr()
    assert main([*cmd, "--resume", "--seed", "2"]) == 2
    err = capsys.readouterr().err
    assert "started with seed 1" in err and "ckpt.pt" in err, err
    assert load_file(tmp_path / "cli" / "ckpt.pt")["state"]["step"] == 1          # nothing trained, nothing written
    assert main([*cmd, "--resume"]) == 0
    st = load_file(tmp_path / "cli" / "ckpt.pt")["state"]
    assert (st["step"], st["seed"]) == (2, 1)

"""The signal matrix: SIGINT and SIGTERM at every stage of `hgca complete` and `hgca drive` end the process within
2 s with exit 130 / 143 and the one-line message, leave no file under a final name (nor a temp file), leave the
input untouched, and a drive stopped anywhere resumes to the same bytes as a drive never stopped.

Each case starts the CLI with `--progress jsonl`, waits for the first record of its stage (the process is then
inside that stage) and sends the signal. The stages a short `complete` passes too fast to hit reliably (the
write, guarded by `AtomicBatch`) are covered by `test_signals.py`'s in-process cases."""
from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent / "drive"))
from drive_data import write_drive  # noqa: E402

from hgca_core.models.gca import GCAConfig, GCAKernel  # noqa: E402
from hgca_core.training.export import save_weights

pytestmark = pytest.mark.slow    # ~30 processes: `make test-slow` (CI runs it)

CODES = {signal.SIGINT: 130, signal.SIGTERM: 143}
NAMES = {signal.SIGINT: "interrupted (SIGINT)", signal.SIGTERM: "terminated (SIGTERM)"}
SIGNALS = [pytest.param(signal.SIGINT, id="SIGINT"), pytest.param(signal.SIGTERM, id="SIGTERM")]
# the full stage with short chains: every stage of a completion in ~20 s on one thread
COMPLETE = ["--stage", "full", "--t1", "4", "--t2", "3", "--samples", "2"]
COMPLETE_STAGES = ["read", "free space", "voxelise", "planner", "coarse", "fine", "mesh"]
DRIVE = ["--size", "12.8", "--overlap", "3.2", "--stage", "coarse", "--t1", "3", "--threads", "1", "--samples", "2"]
DRIVE_STAGES = ["read", "tile", "merge"]


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def tree(folder: Path) -> dict[str, str]:
    """Every file under `folder` (hidden temp files too) with its sha256."""
    return {str(p.relative_to(folder)): digest(p) for p in sorted(folder.rglob("*")) if p.is_file()}


def start(command: str, *args, cwd: Path) -> subprocess.Popen:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "hgca_core.cli", command, *map(str, args), "--progress", "jsonl"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=cwd)


def stop_at(proc: subprocess.Popen, stage: str, sig: int) -> tuple[float, str, list[dict]]:
    """Send `sig` on the first record of `stage`; (seconds it took to end, stderr, every record seen)."""
    seen: list[dict] = []
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            proc.kill()
            pytest.fail(f"process ended (exit {proc.wait()}) before stage {stage!r}: {[r['stage'] for r in seen]}")
        seen.append(json.loads(line))
        if seen[-1]["stage"] == stage:
            break
    else:
        proc.kill()
        pytest.fail(f"no {stage!r} record within 240 s")
    proc.send_signal(sig)
    sent = time.monotonic()
    try:
        rest, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    seen += [json.loads(line) for line in rest.splitlines() if line.strip()]
    return time.monotonic() - sent, err, seen


def check_stopped(proc: subprocess.Popen, command: str, sig: int, took: float, err: str, seen: list[dict]) -> None:
    assert proc.returncode == CODES[sig], (proc.returncode, err[-2000:])
    assert took < 2.0, f"took {took:.2f} s to stop"
    assert err.strip().splitlines() == [f"hgca {command}: {NAMES[sig]}"], err[-2000:]
    assert not [r for r in seen if r["stage"] == "done"]


@pytest.fixture(scope="module")
def street(tmp_path_factory) -> Path:
    """A 40 x 40 m street (ground and a wall) seen from one sensor."""
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(-18, 18, (30_000, 2)), rng.normal(0, 0.02, 30_000)]
    wall = np.c_[rng.uniform(-18, 18, 8000), np.full(8000, 7.0), rng.uniform(0, 5, 8000)]
    path = tmp_path_factory.mktemp("street") / "street.npz"
    np.savez(path, points=np.concatenate([ground, wall]), origins=np.array([[0.0, 0.0, 1.8]]))
    return path


@pytest.mark.parametrize("sig", SIGNALS)
@pytest.mark.parametrize("stage", COMPLETE_STAGES)
def test_complete_stops_at_every_stage(street, tmp_path, stage, sig):
    before = digest(street)
    out = tmp_path / "out"
    out.mkdir()
    proc = start("complete", street, "-o", out / "mesh.ply", *COMPLETE, cwd=tmp_path)
    took, err, seen = stop_at(proc, stage, sig)
    check_stopped(proc, "complete", sig, took, err, seen)
    assert tree(out) == {}, "no mesh and no temp file"
    assert digest(street) == before


@pytest.fixture(scope="module")
def drive_weights(tmp_path_factory) -> Path:
    """Small untrained coarse weights: the drive's plumbing, fast."""
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("w") / "coarse_small.pt"
    save_weights(path, GCAKernel(GCAConfig(channels=(8, 8, 16, 16, 16), steps=3)), {"stage": "test"})
    return path


@pytest.fixture(scope="module")
def drive_inputs(tmp_path_factory, drive_weights):
    """A 40 m drive of 11 scans with its poses, and the bytes of the drive never stopped."""
    root = tmp_path_factory.mktemp("drive")
    scans, poses = write_drive(root / "scans", length=40.0)
    args = [*scans, "--poses", poses, "--weights", drive_weights, *DRIVE]
    whole = root / "whole"
    done = subprocess.run([sys.executable, "-m", "hgca_core.cli", "drive", *map(str, args), "--out", str(whole),
                           "--progress", "none"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    return args, [*scans, poses], {n: h for n, h in tree(whole).items() if n.startswith("drive_s")}


def inputs_digest(paths) -> dict[str, str]:
    return {str(p): digest(Path(p)) for p in paths}


@pytest.mark.parametrize("sig", SIGNALS)
@pytest.mark.parametrize("stage", DRIVE_STAGES)
def test_drive_stops_at_every_stage_and_resumes_to_the_same_bytes(drive_inputs, tmp_path, stage, sig):
    args, inputs, whole = drive_inputs
    before = inputs_digest(inputs)
    out = tmp_path / "drive"
    proc = start("drive", *args, "--out", out, cwd=tmp_path)
    took, err, seen = stop_at(proc, stage, sig)
    check_stopped(proc, "drive", sig, took, err, seen)
    files = tree(out) if out.exists() else {}
    assert not [n for n in files if n.startswith("drive_s")], "no merged mesh under its final name"
    assert not [n for n in files if n.endswith(".tmp")], "no temp file left"
    if files:
        assert json.loads((out / "drive.json").read_text())["status"] == "interrupted"
    assert inputs_digest(inputs) == before
    rerun = subprocess.run([sys.executable, "-m", "hgca_core.cli", "drive", *map(str, args), "--out", str(out),
                            "--progress", "none"], capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 0, rerun.stderr[-2000:]
    assert {n: h for n, h in tree(out).items() if n.startswith("drive_s")} == whole

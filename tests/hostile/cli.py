"""Hostile command lines: flags out of range, outputs that would replace inputs, hangs, checks made too late,
disk full, signals. Each case appends to cases.CASES."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from .cases import case, complete_cmd, good_npz, special_file_cases

LONG = "a" * 246   # with an extension the name fits NAME_MAX (255), its temp file while writing does not
NO_WRITE = "nothing was written"


def nuscenes_folder(d: Path, sweeps: int = 2) -> Path:
    """A folder of nuScenes sweeps (x, y, z, intensity, ring as float32) with its own poses.json."""
    root = d / "nusc"
    root.mkdir()
    rng = np.random.default_rng(5)
    entries = []
    for i in range(sweeps):
        name = f"n{i:03d}__LIDAR_TOP__{1532402927647951 + i * 50_000}.pcd.bin"
        pts = np.c_[rng.uniform(-15, 15, (4000, 2)), rng.normal(0, 0.05, 4000), np.zeros((4000, 2))]
        pts.astype("<f4").tofile(root / name)
        pose = np.eye(4)
        pose[0, 3] = i * 0.5
        entries.append({"file": name, "pose": pose.tolist()})
    (root / "poses.json").write_text(json.dumps({"scans": entries}))
    return root


def drive_cmd(d: Path, *extra) -> list[str]:
    return ["drive", str(good_npz(d)), "--out", str(d / "drive"), "--progress", "none", *map(str, extra)]


def weights_file(d: Path, config: dict | None = None, fill: float | None = None) -> Path:
    """The shipped coarse weights with config entries replaced or every tensor set to `fill`."""
    import torch

    from hgca_core.models.weights import load_file, save_file, shipped

    blob = load_file(shipped("coarse"))
    blob = {**blob, "config": {**blob["config"], **(config or {})}}
    if fill is not None:
        blob["state_dict"] = {k: torch.full_like(v, fill) if v.is_floating_point() else v
                              for k, v in blob["state_dict"].items()}
    return save_file(blob, d / "w.pt")


# --- data loss: an output that is an input, or a file of an input folder --------------------------------------

@case("poses: output is the nuscenes folder's own poses.json", "overwrite an input", group="outputs")
def _(d):
    root = nuscenes_folder(d)
    return ["poses", str(root), "--frames", "0:1", "-o", str(root / "poses.json")]


@case("read: output is an existing file of the nuscenes folder", "input folder", group="outputs")
def _(d):
    root = nuscenes_folder(d)
    (root / "notes.npz").write_bytes(b"kept")
    return ["read", str(root), "--frames", "0:2", "-o", str(root / "notes.npz")]


@case("complete: sample 0 is a sweep file's poses in the nuscenes folder", "overwrite an input", group="outputs")
def _(d):
    root = nuscenes_folder(d)
    os.link(root / "poses.json", root / "m_s0.npz")
    return ["complete", str(root), "--frames", "0:2", "-o", str(root / "m.npz"), "--progress", "none"]


@case("eval-real: output is the nuscenes folder's poses.json", "overwrite an input", group="outputs")
def _(d):
    root = nuscenes_folder(d)
    return ["eval-real", str(root), "--frames", "0:2", "--out", str(root / "poses.json"), "--no-render"]


@case("drive: --out is the input sequence folder", "input sequence folder", group="outputs")
def _(d):
    root = nuscenes_folder(d)
    return ["drive", str(root), "--out", str(root), "--progress", "none"]


@case("synth: --out is an existing file", "exists and is not a folder", group="outputs")
def _(d):
    (d / "scene").write_text("mine")
    return ["synth", "--seed", "1", "--out", str(d / "scene")]


@case("synth: --out under a file", "under a file", group="outputs")
def _(d):
    (d / "scene").write_text("mine")
    return ["synth", "--seed", "1", "--out", str(d / "scene" / "inner")]


@case("demo: --out is an existing file", "exists and is not a folder", group="outputs")
def _(d):
    (d / "demo").write_text("mine")
    return ["demo", "--out", str(d / "demo"), "--progress", "none"]


# --- no --out: a command that writes results never writes into the current folder unasked ------------------

REQUIRED = "required: -o/--out"
for _cmd, _expect, _build in (
        ("eval-real", REQUIRED, lambda d: ["eval-real", str(good_npz(d)), "--methods", "input", "--no-render"]),
        ("bench", REQUIRED, lambda d: ["bench", "--widths", "", "--no-default"]),
        ("demo", REQUIRED, lambda d: ["demo", "--progress", "none"]),
        ("synth", REQUIRED, lambda d: ["synth", "--seed", "1"]),
        ("complete", REQUIRED, lambda d: ["complete", str(good_npz(d)), "--progress", "none"]),
        ("drive", "--out DIR is required", lambda d: ["drive", str(good_npz(d)), "--progress", "none"]),
        ("train", REQUIRED, lambda d: ["train", "--data", str(d), "--max-steps", "1", "--no-progress"])):
    case(f"{_cmd}: no --out", _expect, group="outputs")(_build)


# --- names too long, checked before any work (sample and temp names included) ---------------------------------

@case("drive: --out folder name of 300 characters", "too long", group="outputs")
def _(d):
    return drive_cmd(d)[:-4] + ["--out", str(d / ("b" * 300)), "--progress", "none"]


@case("synth: --out folder name of 300 characters", "too long", group="outputs")
def _(d):
    return ["synth", "--seed", "1", "--out", str(d / ("s" * 300))]


@case("eval: --out name of 252 characters", "too long", group="outputs")
def _(d):
    return ["eval", "--data", str(d), "--out", str(d / f"{LONG}.json")]


# --- seeds that overflow 64 bits ---------------------------------------------------------------------------------

for _cmd, _build in (("complete", lambda d, *f: complete_cmd(good_npz(d), d, *f)), ("drive", drive_cmd),
                     ("eval", lambda d, *f: ["eval", "--data", str(d), *f]),
                     ("eval-real", lambda d, *f: ["eval-real", str(good_npz(d)), *f]),
                     ("synth", lambda d, *f: ["synth", *f, "--out", str(d / "s")]),
                     ("demo", lambda d, *f: ["demo", *f, "--out", str(d / "demo")])):
    case(f"{_cmd}: --seed 2**70", "2**63 - 1", group="flags")(lambda d, b=_build: b(d, "--seed", str(2**70)))
    case(f"{_cmd}: --seed -1", "between 0 and", group="flags")(lambda d, b=_build: b(d, "--seed", "-1"))
for _cmd, _build in (("complete", lambda d, *f: complete_cmd(good_npz(d), d, *f)),
                     ("eval", lambda d, *f: ["eval", "--data", str(d), *f]),
                     ("demo", lambda d, *f: ["demo", *f, "--out", str(d / "demo")])):
    case(f"{_cmd}: --seed 2**63-1 --samples 2", "past 2**63 - 1", group="flags")(
        lambda d, b=_build: b(d, "--seed", str(2**63 - 1), "--samples", "2"))
    case(f"{_cmd}: --seed 2**64-1 --samples 2", "2**63 - 1", group="flags")(
        lambda d, b=_build: b(d, "--seed", str(2**64 - 1), "--samples", "2"))


# --- counts, steps, faces, devices -------------------------------------------------------------------------------

def flags(command: str, build, cases: dict[str, tuple[list[str], str]]) -> None:
    for label, (extra, expect) in cases.items():
        case(f"{command}: {label}", expect, group="flags")(lambda d, b=build, e=extra: b(d, *e))


flags("drive", drive_cmd, {
    "--device tpu": (["--device", "tpu"], "unknown device"),
    "--device CPU": (["--device", "CPU"], "unknown device"),
    "--device cuda:99": (["--device", "cuda:99"], "CUDA GPU"),
    "--max-faces -5": (["--max-faces", "-5"], "max-faces"),
    "--max-faces 10": (["--max-faces", "10"], "at least 1000"),
    "--t1 -1": (["--t1", "-1"], "--t1"),
    "--t2 1e9": (["--t2", "1000000000"], "at most 1000"),
    "--samples 0": (["--samples", "0"], "--samples"),
    "--workers 0": (["--workers", "0"], "--workers"),
    "--threads 0": (["--threads", "0"], "--threads"),
    "--scans-per-tile 0": (["--scans-per-tile", "0"], "--scans-per-tile"),
    "--tile-memory -1": (["--tile-memory", "-1"], "--tile-memory"),
    "--tile-memory nan": (["--tile-memory", "nan"], "--tile-memory"),
    "--size inf": (["--size", "inf"], "--size"),
    "--size nan": (["--size", "nan"], "--size"),
    "--size -12.8": (["--size", "-12.8"], "--size"),
    "--overlap 0": (["--overlap", "0"], "--overlap"),
    "--overlap above --size": (["--size", "12.8", "--overlap", "13"], "--overlap"),
    "--overlap 12.79999 --size 12.8 (a 10 um stride)": (["--size", "12.8", "--overlap", "12.79999"],
                                                         "between tiles"),
    "--plan-only with a 10 um stride": (["--size", "12.8", "--overlap", "12.79999", "--plan-only"],
                                        "between tiles"),
})
flags("complete", lambda d, *f: complete_cmd(good_npz(d), d, *f), {
    "--max-faces -5": (["--max-faces", "-5"], "max-faces"),
    "--t1 1e9 steps": (["--t1", "1000000000"], "at most 1000"),
    "--samples 100000": (["--samples", "100000"], "--samples"),
    "--region 100000 m tall": (["--region", "3,3,1,6,6,100000,0"], "GiB"),
})
flags("eval", lambda d, *f: ["eval", "--data", str(d), *f], {
    "--samples 0": (["--samples", "0"], "--samples"),
    "--count 0": (["--count", "0"], "--count"),
})
flags("eval-real", lambda d, *f: ["eval-real", str(good_npz(d)), "--out", str(d / "r.json"), *f], {
    "--threads 0": (["--threads", "0"], "--threads"),
    "--t1 -1": (["--t1", "-1"], "--t1"),
})
flags("bench", lambda d, *f: ["bench", "--out", str(d / "b"), *f], {
    "--widths abc": (["--widths", "abc"], "--widths"),
    "--widths 40,-60": (["--widths", "40,-60"], "--widths"),
    "--widths nan": (["--widths", "nan"], "--widths"),
})
flags("demo", lambda d, *f: ["demo", *f, "--out", str(d / "demo")], {
    "--samples 0": (["--samples", "0"], "--samples"),
})


# --- weights files: hangs, tracebacks, empty meshes ---------------------------------------------------------------

special_file_cases("flags", lambda d, path: complete_cmd(good_npz(d), d, "--weights", path), [
    ("complete: --weights is a fifo", "not a regular file", "w.pt", "fifo"),
    ("complete: --weights is a symlink loop", "symbolic link loop", "w.pt", "symlink loop"),
    ("complete: --weights is a dangling symlink", "missing target", "w.pt", "dangling symlink"),
])
special_file_cases("flags", lambda d, path: drive_cmd(d, "--weights", path), [
    ("drive: --weights is a fifo", "not a regular file", "w.pt", "fifo"),
])
special_file_cases("flags", lambda d, path: complete_cmd(good_npz(d), d, "--fine-weights", path), [
    ("complete: --fine-weights is a fifo", "not a regular file", "f.pt", "fifo"),
])


@case("complete: weights config steps is a string", "'steps' must be a whole number", group="flags")
def _(d):
    return complete_cmd(good_npz(d), d, "--stage", "coarse", "--weights", weights_file(d, {"steps": "30"}))


@case("complete: weights config asks for 10^9 steps", "'steps' must be between 1 and 1000", group="flags")
def _(d):
    return complete_cmd(good_npz(d), d, "--stage", "coarse", "--weights", weights_file(d, {"steps": 10**9}))


@case("drive: weights config asks for 10^9 steps", "'steps' must be between", group="flags")
def _(d):
    return drive_cmd(d, "--stage", "coarse", "--weights", weights_file(d, {"steps": 10**9}))


@case("complete: weights config alpha0 nan", "'alpha0' must be a finite number", group="flags")
def _(d):
    return complete_cmd(good_npz(d), d, "--stage", "coarse", "--weights", weights_file(d, {"alpha0": float("nan")}))


@case("complete: weights config use_planner is 1", "'use_planner' must be true or false", group="flags")
def _(d):
    return complete_cmd(good_npz(d), d, "--stage", "coarse", "--weights", weights_file(d, {"use_planner": 1}))


@case("complete: all-NaN weights", "NaN or infinite", group="flags")
def _(d):
    return complete_cmd(good_npz(d), d, "--stage", "coarse", "--weights", weights_file(d, fill=float("nan")))


# --- hgca train: every numeric flag and recipe field out of range, bad data folders, outputs over inputs ---------

def train_data(d: Path, splits: tuple[str, ...] = ("train", "val")) -> Path:
    """A dataset folder with one tiny sample per split."""
    from builders import tiny_sample

    root = d / "data"
    for split in splits:
        (root / split).mkdir(parents=True)
        np.savez(root / split / "sample_0000000.npz", **tiny_sample(0))
    return root


def train_cmd(d: Path, *extra: str, data: Path | None = None) -> list[str]:
    return ["train", "--data", str(train_data(d) if data is None else data), "--out", str(d / "run"),
            "--no-progress", *extra]


TRAIN_FLAGS = {   # name: (extra argv, expected message part)
    "--minutes -1": (["--minutes", "-1"], "argument --minutes: must be a finite number of minutes"),
    "--minutes nan": (["--minutes", "nan"], "argument --minutes: must be a finite number of minutes"),
    "--minutes inf": (["--minutes", "inf"], "argument --minutes: must be a finite number of minutes"),
    "--minutes 1e300": (["--minutes", "1e300"], "argument --minutes: must be a finite number of minutes"),
    "--max-steps 0": (["--max-steps", "0"], "argument --max-steps: must be between 1"),
    "--max-steps -3": (["--max-steps", "-3"], "argument --max-steps: must be between 1"),
    "--threads 0": (["--threads", "0"], "argument --threads: must be a whole number between 1"),
    "--threads 99999": (["--threads", "99999"], "argument --threads: must be a whole number between 1"),
    "--seed -1": (["--seed", "-1"], "argument --seed: must be a whole number between 0"),
    "--seed 2**70": (["--seed", str(2**70)], "argument --seed: must be a whole number between 0"),
    "--device tpu": (["--device", "tpu"], "argument --device: unknown device"),
    "--recipe unknown": (["--recipe", "nosuch"], "argument --recipe: invalid choice"),
    "--set batch=0": (["--set", "batch=0"], "recipe field batch must be between 1"),
    "--set batch=10**8": (["--set", "batch=100000000"], "recipe field batch must be between 1"),
    "--set batch=abc": (["--set", "batch=abc"], "--set batch: not a whole number"),
    "--set batch=2.5": (["--set", "batch=2.5"], "--set batch: not a whole number"),
    "--set buffer below batch": (["--set", "batch=4", "--set", "buffer=2"], "recipe field buffer must hold at least"),
    "--set lr=nan": (["--set", "lr=nan"], "--set lr: must be a finite number"),
    "--set lr=inf": (["--set", "lr=inf"], "--set lr: must be a finite number"),
    "--set lr=0": (["--set", "lr=0"], "recipe field lr must be a learning rate above 0"),
    "--set lr=-1e-3": (["--set", "lr=-1e-3"], "recipe field lr must be a learning rate above 0"),
    "--set crop=0": (["--set", "crop=0"], "recipe field crop must be between 8"),
    "--set focus=1.5": (["--set", "focus=1.5"], "recipe field focus must lie in [0, 1]"),
    "--set cut=-0.1": (["--set", "cut=-0.1"], "recipe field cut must lie in [0, 1]"),
    "--set free_weight=-1": (["--set", "free_weight=-1"], "recipe field free_weight must lie in [0"),
    "--set val_every=0": (["--set", "val_every=0"], "recipe field val_every must be a number of minutes"),
    "--set blend=1": (["--set", "blend=1"], "recipe field blend must lie strictly between 0 and 1"),
    "--set precision=fp16": (["--set", "precision=fp16"], "recipe field precision must be fp32 or bf16"),
    "--set channels=8,x": (["--set", "channels=8,x"], "--set channels: expected comma-separated whole numbers"),
    "--set channels=0": (["--set", "channels=0"], "recipe field channels must be widths between 1"),
    "--set free_space=maybe": (["--set", "free_space=maybe"], "--set free_space: expected true or false"),
    "--set unknown key": (["--set", "nosuch=1"], "--set nosuch: no such recipe field"),
    "--set without =": (["--set", "lr"], "--set expects key=value"),
    "--set stage": (["--set", "stage=fine"], "--set stage: the recipe names the stage"),
    "--set twice": (["--set", "lr=1e-4", "--set", "lr=2e-4"], "--set lr given twice"),
    "--set distill without cut": (["--set", "distill=1"], "recipe field distill acts on cut inputs"),
    "--set free_weight without free space": (["--set", "free_weight=2"], "it needs free_space=true"),
    "--set autoencoder on coarse": (["--set", "autoencoder=x.pt"], "recipe field autoencoder is for the fine stage"),
    "--set init_from missing": (["--set", "init_from=missing.pt"], "recipe field init_from: no such weights file"),
    "--minutes 0 without --export": (["--minutes", "0"], "--minutes 0 trains nothing"),
    "--minutes 0 --max-steps": (["--minutes", "0", "--max-steps", "3", "--export"], "a session of 0 minutes"),
    "--minutes 0 --export without a run": (["--minutes", "0", "--export", "w.pt"], "nothing to export"),
}
flags("train", train_cmd, TRAIN_FLAGS)


@case("train: data folder without samples", "no samples in", group="paths")
def _(d):
    (d / "empty" / "train").mkdir(parents=True)
    return train_cmd(d, data=d / "empty")


@case("train: data folder missing", "no samples in", group="paths")
def _(d):
    return train_cmd(d, data=d / "missing")


@case("train: data folder without a val split", "/val; make them with", group="paths")
def _(d):
    return train_cmd(d, data=train_data(d, ("train",)))


@case("train: --out is a file", "--out names a run folder, and this is a file", group="output")
def _(d):
    (d / "run").write_text("not a folder")
    return train_cmd(d)


@case("train: output --export over a data sample", "output would overwrite an input", group="output")
def _(d):
    data = train_data(d)
    return train_cmd(d, "--export", str(data / "train" / "sample_0000000.npz"), data=data)


@case("train: output --export is a folder", "output is an existing folder", group="output")
def _(d):
    (d / "weights").mkdir()
    return train_cmd(d, "--export", str(d / "weights"))


@case("train: output over an existing run without --resume", "--out already holds a run", group="output")
def _(d):
    (d / "run").mkdir()
    (d / "run" / "ckpt.pt").write_bytes(b"an earlier run")
    return train_cmd(d, "--max-steps", "1")


@case("train: --resume of a corrupt checkpoint", "ckpt.pt", group="paths")
def _(d):
    (d / "run").mkdir()
    (d / "run" / "ckpt.pt").write_bytes(b"not a checkpoint")
    return train_cmd(d, "--resume", "--max-steps", "1")

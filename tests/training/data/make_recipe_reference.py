"""Measure `recipe_reference.json`: each shipped recipe run with the flags `hgca train` had before recipes.

The recipes' test (tests/training/test_recipes.py) checks that `hgca train --recipe NAME` reproduces these runs
bit for bit (STEPS steps: weights, their average, logs and the export). The flags' code is the training code at
PRE_RECIPES (commands/train.py, training/coarse.py, training/trainer.py) over today's tree, so a later change to the
numerics elsewhere (the sparse convs, the data) is re-measured by running this again, on one thread:

    .venv/bin/python tests/training/data/make_recipe_reference.py [RECIPE ...]
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
sys.path[:0] = [str(ROOT), str(ROOT / "tests"), str(ROOT / "tests" / "training")]

PRE_RECIPES = "3ba26f3"   # the last commit with `hgca train`'s recipe flags
OLD_FILES = ("hgca_core/commands/train.py", "hgca_core/training/coarse.py", "hgca_core/training/trainer.py")
STEPS = 50
WEIGHTS = {s: str(ROOT / "hgca_core" / "weights" / f"{s}.pt") for s in ("coarse", "coarse_noplanner", "fine",
                                                                          "autoencoder")}
# each shipped recipe as the stage and flags of PRE_RECIPES that made its weights (the weights' metadata)
FLAGS = {
    "coarse-shipped": ["coarse", "--batch", "6", "--free-space", "--free-weight", "8", "--cut", "0.5", "--focus", "0.5",
                       "--precision", "bf16", "--lr", "1.5e-4", "--turn", "0.5", "--cut-free-loss", "--init-from",
                       WEIGHTS["coarse"], "--distill", "1", "--teacher", WEIGHTS["coarse"], "--blend-with",
                       WEIGHTS["coarse"], "--blend-t", "0.3"],
    "coarse-noplanner-shipped": ["coarse-noplanner", "--free-space", "--focus", "0.5", "--precision", "bf16",
                                 "--init-from", WEIGHTS["coarse_noplanner"]],
    "fine-shipped": ["fine", "--free-space", "--precision", "bf16", "--init-from", WEIGHTS["fine"]],
    "autoencoder": ["autoencoder"],
}


def measure(name: str, tree: Path, data: Path, tmp: Path) -> dict:
    """One recipe's run with the old flags in `tree`: its digests and the command that made them."""
    from test_recipes import run_digest

    out, export = tmp / name, tmp / f"{name}.pt"
    stage, *flags = FLAGS[name]
    argv = ["train", stage, "--data", str(data), "--out", str(out), "--max-steps", str(STEPS), "--minutes", "60",
            "--threads", "1", "--no-progress", "--val-every", "1000", *flags, "--export", str(export)]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(tree)}
    import resource
    import time

    t0, r0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([sys.executable, "-m", "hgca_core.cli", *argv], check=True, env=env, cwd=tmp)   # not ROOT: its
    # hgca_core would come first on the path
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    print(f"{name}: {STEPS} steps in {time.perf_counter() - t0:.0f} s wall, "
          f"{r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime:.0f} s CPU", flush=True)
    shown = [a.replace(str(tmp), "TMP").replace(f"{ROOT}/", "") for a in argv]
    return {"command": f"OMP_NUM_THREADS=1 hgca {' '.join(shown)}  (training code of {PRE_RECIPES})", **run_digest(out, export)}


def main(names: list[str]) -> None:
    from hgca_core.io.digest import file_digest
    from test_recipes import cpu_kind, make_dataset

    path = Path(__file__).with_name("recipe_reference.json")
    old = json.loads(path.read_text()) if path.exists() else {}
    runs = old.get("runs", {}) if old.get("steps") == STEPS and old.get("cpu") == cpu_kind() else {}
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "tree"
        shutil.copytree(ROOT / "hgca_core", tree / "hgca_core", ignore=shutil.ignore_patterns("__pycache__"))
        for f in OLD_FILES:
            (tree / f).write_bytes(subprocess.run(["git", "-C", str(ROOT), "show", f"{PRE_RECIPES}:{f}"],
                                                  check=True, capture_output=True).stdout)
        data = make_dataset(Path(tmp) / "data")
        for name in names or list(FLAGS):
            runs[name] = measure(name, tree, data, Path(tmp))
            print(f"measured {name}", flush=True)
    record = {"cpu": cpu_kind(), "steps": STEPS,
              "weights_sha256": {s: file_digest(f) for s, f in WEIGHTS.items()}, "runs": runs}
    path.write_text(json.dumps(record, indent=1) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main(sys.argv[1:])

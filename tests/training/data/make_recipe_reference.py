"""Measure `recipe_reference.json`: the shipped coarse recipe run with the flags `hgca train` had before recipes.

The recipes' test (tests/training/test_recipes.py) checks that `hgca train --recipe coarse-shipped` reproduces
this run bit for bit. The flags' code is the training code at PRE_RECIPES (commands/train.py, training/coarse.py,
training/trainer.py) over today's tree, so a later change to the numerics elsewhere (the sparse convs, the data)
is re-measured by running this again, on one thread:

    .venv/bin/python tests/training/data/make_recipe_reference.py
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
STEPS = 10
WEIGHTS = ROOT / "hgca_core/weights/coarse.pt"
# the recipe of the fine-tune behind the shipped coarse.pt (its metadata), with the flags of PRE_RECIPES
FLAGS = ["--batch", "6", "--free-space", "--free-weight", "8", "--cut", "0.5", "--focus", "0.5", "--precision", "bf16",
         "--lr", "1.5e-4", "--turn", "0.5", "--cut-free-loss", "--init-from", str(WEIGHTS), "--distill", "1",
         "--teacher", str(WEIGHTS), "--blend-with", str(WEIGHTS), "--blend-t", "0.3"]


def main() -> None:
    from hgca_core.hardware import cpu_name
    from hgca_core.io.digest import file_digest
    from test_recipes import make_dataset, run_digest

    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "tree"
        shutil.copytree(ROOT / "hgca_core", tree / "hgca_core", ignore=shutil.ignore_patterns("__pycache__"))
        for f in OLD_FILES:
            (tree / f).write_bytes(subprocess.run(["git", "-C", str(ROOT), "show", f"{PRE_RECIPES}:{f}"],
                                                  check=True, capture_output=True).stdout)
        data = make_dataset(Path(tmp) / "data")
        out, export = Path(tmp) / "run", Path(tmp) / "exported.pt"
        argv = ["train", "coarse", "--data", str(data), "--out", str(out), "--max-steps", str(STEPS), "--minutes",
                "10", "--threads", "1", "--no-progress", "--val-every", "1000", *FLAGS, "--export", str(export)]
        env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(tree)}
        subprocess.run([sys.executable, "-m", "hgca_core.cli", *argv], check=True, env=env, cwd=tmp)
        record = run_digest(out, export)
        shown = [os.path.relpath(a, ROOT) if a.startswith(str(ROOT)) else a.replace(tmp, "TMP") for a in argv]
    record = {"command": f"OMP_NUM_THREADS=1 hgca {' '.join(shown)}  (training code of {PRE_RECIPES})",
              "cpu": cpu_name(), "weights_sha256": file_digest(WEIGHTS), "steps": STEPS, **record}
    path = Path(__file__).with_name("recipe_reference.json")
    path.write_text(json.dumps(record, indent=1) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

"""Completion speed/memory benchmark (run by hand): `python benchmarks/completion.py [hgca bench options]`.

Writes benchmarks/results/completion_<stage>_<device>.{json,md,png} (or where `--out` says); see hgca_core/bench.py."""
import sys
from pathlib import Path

from hgca_core.cli import main

RESULTS = Path(__file__).resolve().parent / "results"

if __name__ == "__main__":
    argv = sys.argv[1:]
    given = any(a in ("-o", "--out") or a.startswith("--out=") for a in argv)
    sys.exit(main(["bench", *argv, *([] if given else ["--out", str(RESULTS)])]))

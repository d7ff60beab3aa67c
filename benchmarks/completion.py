"""Completion speed/memory benchmark (run by hand): `python benchmarks/completion.py [hgca bench options]`.

Writes benchmarks/results/completion_<stage>_<device>.{json,md,png}; see hgca_core/bench.py."""
import sys

from hgca_core.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", *sys.argv[1:]]))

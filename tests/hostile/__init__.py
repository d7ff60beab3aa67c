"""The hostile-input campaign for the `hgca` CLI as data: every case builds its files in an empty folder and returns
the command line, and all expect the same (exit 2, one `error:` line, no traceback, inputs untouched, nothing
written). cases.py holds the table and the bad files of every format; reads.py and cli.py append further classes.
tests/test_hostile_inputs.py runs them in-process; benchmarks/hostile_inputs.py runs them as subprocesses for a
results page (benchmarks may import the tests' builders; tests never import benchmarks)."""
from . import cases, cli, reads  # noqa: F401  (importing reads and cli appends their cases)
from .cases import CASES, Case

__all__ = ["CASES", "Case"]

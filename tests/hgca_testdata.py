"""The tests' way to the shared builders and to the real LiDAR fixtures (importable from any test as
`hgca_testdata`). The builders a benchmark also needs (the tiny synthetic sample, LAS files, the real sweeps, a
folder's state) live once in tests/builders.py, re-exported here; benchmarks import that module (never this one:
it imports pytest). What is pytest's (skip or fail on a missing fixture, a tmpfs) stays here. Tests never import
benchmarks/ (tests/test_layering.py)."""
from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from builders import REAL_FIXTURES, UTM_OFFSETS, folder_state, tiny_sample, with_distance_pairs, write_las

__all__ = ["REAL_FIXTURES", "UTM_OFFSETS", "folder_state", "in_ci", "refusal", "require_real", "small_tmpfs", "tiny_sample",
           "tiny_scan_file", "with_distance_pairs", "write_las"]


def in_ci() -> bool:
    """True when the environment variable CI is set (to anything but '', 0, false or no)."""
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


def require_real(path: Path | None = None) -> Path:
    """A real LiDAR fixture (default: the folder tests/data/real). When it is missing the test is skipped on a
    developer's machine (e.g. a checkout that left the data out), but FAILS under CI: a clone holds the folder,
    so a missing fixture there means the real-file tests silently stopped running."""
    p = REAL_FIXTURES if path is None else Path(path)
    if not p.exists():
        msg = f"real LiDAR fixture missing: {p} (expected in tests/data/real)"
        if in_ci():
            pytest.fail(f"{msg}; CI is set, so this is a failure, not a skip", pytrace=False)
        pytest.skip(msg)
    return p


@contextlib.contextmanager
def small_tmpfs(root: Path, size: str):
    """`root` made a tmpfs of `size` (e.g. "64k": a real ENOSPC once full) for the block; a skip where mounting is
    not allowed (not root, no mount)."""
    import shutil
    import subprocess

    root.mkdir()
    if shutil.which("mount") is None or os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(root)], capture_output=True)
    if res.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {res.stderr.decode()[:200]}")
    try:
        yield root
    finally:
        subprocess.run(["umount", str(root)], capture_output=True)


def refusal(read: Callable[[Path], object], path: Path, problem: str) -> str:
    """The InputError message of `read(path)`, checked to name the problem (a regular expression) and the file."""
    from hgca_core.errors import InputError

    with pytest.raises(InputError, match=problem) as exc:
        read(path)
    message = str(exc.value)
    assert path.name in message, message
    return message


def tiny_scan_file(folder: Path) -> Path:
    """tiny_sample(3)'s input as a user's scan file: world points 100 / 200 / -1 m from its region frame, with its
    sensor origin (the region "103,203,1,6,6,4" holds it)."""
    s = tiny_sample(3)
    path = folder / "scan.npz"
    world = s["input_points"].astype(np.float64) + np.array([100.0, 200.0, -1.0])
    np.savez(path, points=world, origins=np.array([[103.0, 203.0, 2.0]]))
    return path

"""Outputs never replace an input and are checked before any work (issue 11, item 2).

Each case runs the real CLI entry point and asserts exit 2, a message naming the output, and that every input
file is byte-for-byte unchanged. The `complete` cases use `--progress jsonl` to show that the refusal comes
before reading: the only record is the error.
"""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from hgca_core.cli import main


def run_cli(monkeypatch, capsys, *argv) -> tuple[int, str, str]:
    monkeypatch.setattr(sys, "argv", ["hgca"])
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def scan(tmp_path) -> Path:
    path = tmp_path / "a_s0.npz"
    np.savez(path, points=np.random.default_rng(0).uniform(0, 5, (200, 3)))
    return path


def digest(paths) -> dict[str, bytes]:
    return {str(p): Path(p).read_bytes() for p in paths}


def refused(code: int, out: str, err: str, what: str) -> None:
    assert code == 2, err
    assert what in err and "Traceback" not in err, err
    records = [json.loads(line) for line in out.splitlines()]
    assert [r["stage"] for r in records] in ([], ["error"]), out  # nothing was read or computed first


@pytest.mark.parametrize("how", ["same name", "sample name", "symlink", "dotdot", "hard link"])
def test_output_that_is_an_input_is_refused(tmp_path, monkeypatch, capsys, scan, how):
    if how == "same name":
        argv = ["read", scan, "-o", scan]
    elif how == "sample name":  # `complete a_s0.npz -o a.npz` would write its sample 0 to a_s0.npz
        argv = ["complete", scan, "-o", tmp_path / "a.npz", "--progress", "jsonl"]
    elif how == "symlink":
        (tmp_path / "link.npz").symlink_to(scan)
        argv = ["read", scan, "-o", tmp_path / "link.npz"]
    elif how == "dotdot":
        (tmp_path / "sub").mkdir()
        argv = ["read", scan, "-o", tmp_path / "sub" / ".." / scan.name]
    else:
        os.link(scan, tmp_path / "b_s0.npz")
        argv = ["complete", scan, "-o", tmp_path / "b.npz", "--progress", "jsonl"]
    before = digest([scan])
    code, out, err = run_cli(monkeypatch, capsys, *argv)
    refused(code, out, err, "output would overwrite an input file")
    assert digest([scan]) == before


def test_poses_file_and_weights_count_as_inputs(tmp_path, monkeypatch, capsys, scan):
    poses = tmp_path / "p_s0.npz"  # an odd name for a poses file, but it must not be replaced either
    poses.write_text(json.dumps({"scans": [{"file": scan.name, "pose": np.eye(4).tolist()}]}))
    before = digest([scan, poses])
    code, out, err = run_cli(monkeypatch, capsys, "complete", scan, "--poses", poses, "-o", tmp_path / "p.npz",
                             "--progress", "jsonl")
    refused(code, out, err, "p_s0.npz: output would overwrite an input file")
    weights = tmp_path / "w_s0.npz"
    weights.write_bytes(b"not really weights")
    code, out, err = run_cli(monkeypatch, capsys, "complete", scan, "--weights", weights, "-o", tmp_path / "w.npz",
                             "--progress", "jsonl")
    refused(code, out, err, "w_s0.npz: output would overwrite an input file")
    assert digest([scan, poses]) == before and weights.read_bytes() == b"not really weights"


@pytest.mark.parametrize("command", ["read", "complete"])
@pytest.mark.parametrize("place, message", [
    ("folder", "output is an existing folder"),
    ("missing", "output folder does not exist"),
    ("under a file", "output folder is not a folder"),
    ("unwritable", "cannot write in the output folder"),
])
def test_unusable_output_place_is_refused_before_reading(tmp_path, monkeypatch, capsys, scan, command, place,
                                                          message):
    name = "out_s0.npz" if command == "complete" else "out.npz"  # the file `complete -o out.npz` writes first
    if place == "folder":
        (tmp_path / name).mkdir()
        out = tmp_path / "out.npz"
    elif place == "missing":
        out = tmp_path / "nowhere" / "out.npz"
    elif place == "under a file":
        (tmp_path / "plain.txt").write_text("x")
        out = tmp_path / "plain.txt" / "out.npz"
    else:
        if not Path("/proc/self").is_dir():
            pytest.skip("needs Linux /proc as a place nobody can create files in, root included")
        out = Path("/proc/hgca_out.npz")
    extra = ["--progress", "jsonl"] if command == "complete" else []
    code, stdout, err = run_cli(monkeypatch, capsys, command, scan, "-o", out, *extra)
    refused(code, stdout, err, message)
    if command == "read":
        assert stdout == ""  # `read` prints its summary only after reading

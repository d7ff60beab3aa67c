"""A drive folder damaged between runs or on a full disk: a cache entry cut short is recomputed with a warning
(not a BadZipFile traceback), and a full disk is one error line with no second failure after it."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

import hgca_core
from drive_data import write_drive
from hgca_core.tiling.store import DriveStore

SMALL = {"size": 12.8, "overlap": 3.2, "stage": "coarse", "t1": 3, "threads": 1}
CLI_SMALL = ["--size", "12.8", "--overlap", "3.2", "--stage", "coarse", "--t1", "3", "--threads", "1"]


def test_a_truncated_cache_entry_is_recomputed_with_a_warning(drive_weights, tmp_path, capsys):
    from hgca_core.cli import main

    scans, poses = write_drive(tmp_path / "scans", length=8.0)
    out = tmp_path / "drive"
    first = hgca_core.drive(scans, out, poses=poses, weights=str(drive_weights), **SMALL)
    merged = (out / "drive_s0.ply").read_bytes()
    key = first["tiles"][0]["key"]
    entry = out / "cache" / f"{key}.npz"
    whole = entry.read_bytes()
    before = DriveStore(out).load(key)
    entry.write_bytes(whole[: len(whole) // 2])
    argv = ["drive", *map(str, scans), "--poses", str(poses), "--weights", str(drive_weights), *CLI_SMALL,
            "--out", str(out), "--progress", "none"]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "hgca drive: warning: tile 0: its finished result" in err and "unreadable" in err, err
    assert "Traceback" not in err and "error:" not in err, err
    doc = json.loads((out / "drive.json").read_text())
    assert doc["status"] == "complete" and doc["timings"]["tiles_computed"] == 1, "only the damaged tile ran"
    again = DriveStore(out).load(key)                     # the same tile again, saved whole
    for old, new in zip(before["samples"], again["samples"]):
        assert all(np.array_equal(old[n], new[n]) for n in ("vertices", "faces", "observed_distance", "cells"))
    assert (out / "drive_s0.ply").read_bytes() == merged


@pytest.fixture
def small_disk(tmp_path):
    from hgca_testdata import small_tmpfs

    with small_tmpfs(tmp_path / "full", "64k") as root:
        yield root


def test_disk_full_during_a_drive_is_one_error_line(drive_weights, tmp_path, small_disk):
    scans, poses = write_drive(tmp_path / "scans", length=8.0)
    res = subprocess.run([sys.executable, "-m", "hgca_core.cli", "drive", *map(str, scans), "--poses", str(poses),
                          "--weights", str(drive_weights), *CLI_SMALL, "--out", str(small_disk / "drive"),
                          "--progress", "none"], capture_output=True, text=True, timeout=600)
    assert res.returncode == 2, res.stderr[-2000:]
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("hgca drive: error: "), res.stderr
    assert "no space left on the device" in lines[0], res.stderr
    assert not list((small_disk / "drive").rglob("*.tmp")), "no temp file left"

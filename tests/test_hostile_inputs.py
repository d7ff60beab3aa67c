"""The hostile-input campaign of tests/hostile/, each case through the CLI entry point in-process:
exit 2, one clear `error:` line naming the problem, no traceback, inputs untouched, nothing written."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

from hgca_testdata import folder_state
from hostile import CASES, Case
from hgca_core.cli import main


@pytest.mark.parametrize("c", CASES, ids=[c.name for c in CASES])
def test_hostile_input_is_one_clear_error(c: Case, tmp_path, monkeypatch, capsys):
    argv = c.build(tmp_path)
    before = folder_state(tmp_path)
    monkeypatch.setattr(sys, "argv", ["hgca"])
    monkeypatch.chdir(tmp_path)
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse rejected a flag
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2, f"exit {code}: {err[-1500:]}"
    assert "Traceback" not in err and "error:" in err, err
    assert c.expect in err, err
    assert folder_state(tmp_path) == before, "an input changed or an output appeared"


def test_campaign_is_large_and_covers_every_reader():
    names = [c.name for c in CASES]
    assert len(names) == len(set(names))
    assert len(CASES) >= 200
    for fmt in ("ply", "las", "laz", "pcd", "xyz", "csv", "npy", "npz", "kitti", "nuscenes", "poses", "--t1",
                "--device", "output", "one point"):
        assert any(fmt in n for n in names), fmt

"""benchmarks/val_cut.py: the first sweeps it scores, optionally of some sensor profiles only."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import val_cut  # noqa: E402


def _sample(path: Path, k: int) -> None:
    pts = np.arange(12, dtype=np.float64).reshape(4, 3) + k
    np.savez(path, input_points=pts, input_scan_index=np.array([0, 0, 1, 1]),
             input_far_points=pts[:1] + 100, input_far_scan_index=np.array([0]),
             input_origins=np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]) + k)


def test_first_sweeps_keep_scan_zero_and_filter_by_profile(tmp_path):
    val = tmp_path / "val"
    val.mkdir()
    # val seeds 1,000,000 and 1,000,003 draw hdl64, 1,000,001 and 1,000,002 hdl32 (docs/data/synth2f_recipe.json)
    for k in range(4):
        _sample(val / f"sample_{1_000_000 + k}.npz", k)
    every = list(val_cut.first_sweeps(tmp_path, "val", 3))
    assert [s for s, _, _ in every] == ["sample_1000000", "sample_1000001", "sample_1000002"]
    stem, pts, origin = every[1]
    np.testing.assert_array_equal(pts, np.array([[1.0, 2, 3], [4, 5, 6], [101, 102, 103]]))  # scan 0, far hit too
    np.testing.assert_array_equal(origin, [[2.0, 3.0, 4.0]])
    hdl64 = [s for s, _, _ in val_cut.first_sweeps(tmp_path, "val", 4, ["hdl64"])]
    assert hdl64 == ["sample_1000000", "sample_1000003"]
    assert val_cut.write_first_sweeps(tmp_path, 4, tmp_path, ["waymo"]) == []


def test_the_region_turn_reaches_eval_real(tmp_path, monkeypatch):
    """`--yaw` is passed to `hgca eval-real`, which turns the scored region about the sensor (0 by default)."""
    from types import SimpleNamespace

    ran = []
    monkeypatch.setattr(val_cut, "write_first_sweeps", lambda *a: [tmp_path / "s.npz"])
    monkeypatch.setattr(val_cut.subprocess, "run", lambda cmd, check: ran.append(cmd) or SimpleNamespace(returncode=0))
    for extra, want in (([], "0.0"), (["--yaw", "30"], "30.0")):
        assert val_cut.main(["--data", str(tmp_path), "--out", str(tmp_path / "v.json"), *extra]) == 0
        cmd = ran[-1]
        assert "eval-real" in cmd and cmd[cmd.index("--yaw") + 1] == want


def test_the_command_other_benchmarks_build_is_one_this_script_runs(tmp_path, monkeypatch):
    """`command` (keep_sweep's and screen's subprocess line) names this file and options its parser takes, and each
    of them reaches the sweeps written or `hgca eval-real`."""
    from types import SimpleNamespace

    ran, wrote = [], []
    monkeypatch.setattr(val_cut, "write_first_sweeps", lambda *a: wrote.append(a) or [tmp_path / "s.npz"])
    monkeypatch.setattr(val_cut.subprocess, "run", lambda cmd, check: ran.append(cmd) or SimpleNamespace(returncode=0))
    cmd = val_cut.command(tmp_path / "w.pt", tmp_path / "v.json", str(tmp_path), 5, count=7, yaw=30, threads=2)
    assert Path(cmd[1]) == Path(val_cut.__file__).resolve()
    assert val_cut.main(cmd[2:]) == 0
    assert wrote[-1][:2] == (tmp_path, 7)
    real = ran[-1]
    for flag, want in (("--samples", "5"), ("--yaw", "30.0"), ("--threads", "2"), ("--weights", str(tmp_path / "w.pt")),
                       ("--out", str(tmp_path / "v.json"))):
        assert real[real.index(flag) + 1] == want, flag

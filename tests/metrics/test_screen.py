"""benchmarks/screen.py: both val settings scored once per weights file, then judged clause by clause."""
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import screen  # noqa: E402
from test_cut_frontier import _result  # noqa: E402  (the results-file builder the frontier tests use)

# per weights file and yaw: mean (recall, above-cut share, cells above) over two val sweeps
SCORES = {("a", 0.0): (0.72, 0.05, 100.0), ("a", 30.0): (0.60, 0.04, 90.0),
          ("b", 0.0): (0.65, 0.03, 80.0), ("b", 30.0): (0.58, 0.07, 70.0)}


def _fake_scoring(ran, scores):
    def run_all(cmds, n):
        for c in cmds:
            out, yaw = Path(c[c.index("--out") + 1]), float(c[c.index("--yaw") + 1])
            name = Path(c[c.index("--weights") + 1]).stem
            ran.append((name, yaw))
            r, a, g = scores[(name, yaw)]
            _result(out, {"s1": (r - 0.1, a, g), "s2": (r + 0.1, a, g)})
        return True
    return run_all


def test_each_row_is_scored_in_both_settings_once_and_judged_by_the_clauses_it_fails(tmp_path, monkeypatch):
    ran, scores = [], dict(SCORES)
    monkeypatch.setattr(screen, "run_all", _fake_scoring(ran, scores))
    for n in ("a", "b"):
        (tmp_path / f"{n}.pt").write_bytes(b"w")
    prefix = str(tmp_path / "s")
    args = ["--count", "2", "--samples", "2", "--row", f"a={tmp_path / 'a.pt'}", "--row", f"b={tmp_path / 'b.pt'}",
            "--prefix", prefix, "--recall-min", "71", "--share-max", "7.1", "--yaw30-share-max", "5.8"]
    assert screen.main(args) == 0
    assert sorted(ran) == [("a", 0.0), ("a", 30.0), ("b", 0.0), ("b", 30.0)]
    doc = json.loads(Path(prefix + "_screen.json").read_text())["screen"]
    assert doc["a"]["val"] == [72.0, 5.0, 100.0] and doc["a"]["fails"] == []
    assert doc["b"]["fails"] == ["yaw-0 recall 65.0 < 71", "yaw-30 share 7.0 > 5.8"]
    md = Path(prefix + "_screen.md").read_text()
    assert "| a | 72.0 / 5.0 / 100 | 60.0 / 4.0 / 90 | passes |" in md
    ran.clear()                                     # a second screen with one more row scores only the new row
    (tmp_path / "c.pt").write_bytes(b"w")
    scores.update({("c", 0.0): (0.8, 0.02, 50.0), ("c", 30.0): (0.7, 0.02, 50.0)})
    assert screen.main([*args, "--row", f"c={tmp_path / 'c.pt'}"]) == 0
    assert sorted(ran) == [("c", 0.0), ("c", 30.0)]
    ran.clear()                                     # a file a stopped screen left with one sweep of two is scored again
    doc = json.loads(Path(prefix + "_valyaw30_b.json").read_text())
    doc["inputs"].pop("s2")
    Path(prefix + "_valyaw30_b.json").write_text(json.dumps(doc))
    assert screen.main(args) == 0
    assert ran == [("b", 30.0)]


def test_a_failed_scoring_or_a_bad_row_stops_the_screen(tmp_path, monkeypatch, capsys):
    import pytest

    monkeypatch.setattr(screen, "run_all", lambda cmds, n: False)
    (tmp_path / "a.pt").write_bytes(b"w")
    assert screen.main(["--row", f"a={tmp_path / 'a.pt'}", "--prefix", str(tmp_path / "s")]) == 2
    assert not (tmp_path / "s_screen.md").exists()
    for row in (f"a b={tmp_path / 'a.pt'}", "a=missing.pt"):
        with pytest.raises(SystemExit) as e:
            screen.main(["--row", row, "--prefix", str(tmp_path / "s")])
        assert e.value.code == 2 and "expected NAME=WEIGHTS" in capsys.readouterr().err

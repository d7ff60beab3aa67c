"""benchmarks/run_spread.py: the spread between training runs of one recipe beside each run's own standard error."""
import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import run_spread  # noqa: E402
from test_cut_frontier import _run as _samples  # noqa: E402  (the eval-real results builder)


def _run(path: Path, seed: int, shares: list[float]) -> str:
    """`_samples`' results file with each row's summary filled in, as `hgca eval-real` writes it."""
    from hgca_core.metrics.realscan import summarise

    doc = json.loads(Path(_samples(path, seed, shares)).read_text())
    for res in doc["inputs"].values():
        for case in res["cases"].values():
            for row in case["rows"].values():
                row["summary"] = summarise(row["per_sample"])
    path.write_text(json.dumps(doc))
    return str(path)


def test_runs_apart_by_more_than_their_errors_show_a_ratio_above_one(tmp_path):
    # recipe A: two runs 4 points apart (shares 10 +- 1 and 14 +- 1, recall 0.4 + share); the second pooled from
    # two files of disjoint seeds. Recipe B: one run (no spread to measure)
    a1 = _run(tmp_path / "a1.json", 0, [0.09, 0.11])
    a2 = _run(tmp_path / "a2s0.json", 0, [0.13])
    a2b = _run(tmp_path / "a2s1.json", 1, [0.15])
    b1 = _run(tmp_path / "b1.json", 0, [0.20, 0.20])
    out = tmp_path / "spread.json"
    assert run_spread.main(["--group", f"A={a1},{a2}+{a2b}", "--group", f"B={b1}", "--out", str(out)]) == 0
    s = json.loads(out.read_text())["spread"]["av2_log"]
    a, b = s["A"], s["B"]
    assert [r["share"] for r in a["runs"]] == pytest.approx([10.0, 14.0]) and [r["k"] for r in a["runs"]] == [2, 2]
    assert a["share_mean"] == pytest.approx(12.0) and a["recall_mean"] == pytest.approx(52.0)
    assert a["share_sd"] == pytest.approx(2 * 2 ** 0.5)          # two runs 4 apart: sd 4 / sqrt 2
    assert a["share_sem_within"] == pytest.approx(1.0)           # each run: two samples 1 point either side
    assert a["ratio"] == pytest.approx(2 * 2 ** 0.5)
    assert b["share_sd"] is None and b["ratio"] is None and b["share_mean"] == pytest.approx(20.0)
    md = out.with_suffix(".md").read_text()
    assert "| av2_log | A | 2 | 50.0, 54.0 | 10.0 ± 1.0, 14.0 ± 1.0 | 52.0 / 2.8 | 12.0 / 2.8 | 1.0 | 2.83 |" in md
    assert "| av2_log | B | 1 |" in md and "20.0 / -" in md
    assert out.with_suffix(".png").stat().st_size > 10_000


def test_bad_groups_and_an_output_over_an_input_are_refused(tmp_path, capsys):
    a = _run(tmp_path / "a.json", 0, [0.1, 0.1])
    for bad, said in (("A", "expected NAME=RUN.json"), ("=x.json", "expected NAME=RUN.json"),
                      (f"A={tmp_path / 'missing.json'}", "missing.json")):
        with pytest.raises(SystemExit) as e:
            run_spread.main(["--group", bad, "--out", str(tmp_path / "s.json")])
        assert e.value.code == 2 and said in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        run_spread.main(["--group", f"A={a}", "--out", a])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "error: --out" in err and "overwrite an input" in err
    assert json.loads(Path(a).read_text())["config"]["seed"] == 0     # the input kept

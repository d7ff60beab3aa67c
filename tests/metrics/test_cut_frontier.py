"""benchmarks/cut_frontier.py: rows scored before, as points per input set, a table and a plot."""
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import cut_frontier  # noqa: E402


def _result(path: Path, inputs: dict[str, tuple[float, float, float]]) -> str:
    """A val_cut.py / eval-real JSON holding, per input, mean (recall, above-cut share, cells above) of cut 2 m."""
    def s(v):
        return {"min": v, "mean": v, "max": v, "spread": 0.0}

    doc = {"inputs": {name: {"cases": {
        "full": {"rows": {"hgca": {"summary": {"empty_share": s(0.05)}}}},
        "cut_2": {"rows": {"hgca": {"summary": {"recall": s(r), "above_empty_share": s(a), "generated_above": s(g)}}}},
    }} for name, (r, a, g) in inputs.items()}}
    path.write_text(json.dumps(doc))
    return str(path)


def test_val_sweeps_are_averaged_real_logs_kept_apart_and_every_row_is_drawn(tmp_path):
    rows = []
    for label, shift in (("shipped", 0.0), ("candidate", 0.1)):
        val = _result(tmp_path / f"val_{label}.json", {"sample_1": (0.6 + shift, 0.10, 100.0),
                                                        "sample_2": (0.4 + shift, 0.20, 300.0)})
        real = _result(tmp_path / f"real_{label}.json", {"av2_log": (0.45, 0.08 + shift, 50.0)})
        rows += ["--row", f"{label}={val},{real}"]
    out = tmp_path / "frontier.json"
    assert cut_frontier.main([*rows, "--val-name", "av2 val", "--out", str(out)]) == 0
    pts = json.loads(out.read_text())["points"]
    val = pts["av2 val"]
    assert [round(x, 6) for x in val["shipped"]] == [50.0, 15.0, 200.0]
    assert [round(x, 6) for x in val["candidate"]] == [60.0, 15.0, 200.0]
    assert [round(x, 6) for x in pts["av2_log"]["candidate"]] == [45.0, 18.0, 50.0]
    md = out.with_suffix(".md").read_text()
    assert "| candidate | 60.0 / 15.0 / 200 | 45.0 / 18.0 / 50 |" in md
    assert out.with_suffix(".png").stat().st_size > 10_000


def test_a_row_without_two_files_is_refused(tmp_path, capsys):
    import pytest

    with pytest.raises(SystemExit) as e:
        cut_frontier.main(["--row", "shipped=only_one.json", "--out", str(tmp_path / "f.json")])
    assert e.value.code == 2 and "expected LABEL=VAL.json,REAL.json" in capsys.readouterr().err

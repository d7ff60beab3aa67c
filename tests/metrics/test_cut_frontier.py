"""benchmarks/cut_frontier.py: rows scored before, as points per input set, a table and a plot."""
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import cut_frontier  # noqa: E402


def _result(path: Path, inputs: dict[str, tuple[float, float, float]], swing: float = 0.0) -> str:
    """A val_cut.py / eval-real JSON holding, per input, mean (recall, above-cut share, cells above) of cut 2 m,
    over two samples whose shares lie `swing` either side of the mean."""
    def s(v):
        return {"min": v, "mean": v, "max": v, "spread": 0.0}

    doc = {"inputs": {name: {"cases": {
        "full": {"rows": {"hgca": {"summary": {"empty_share": s(0.05)}}}},
        "cut_2": {"rows": {"hgca": {
            "summary": {"recall": s(r), "above_empty_share": s(a), "generated_above": s(g)},
            "per_sample": [{"above_empty_share": a - swing}, {"above_empty_share": a + swing}]}}},
    }} for name, (r, a, g) in inputs.items()}}
    path.write_text(json.dumps(doc))
    return str(path)


def test_val_sweeps_are_averaged_real_logs_kept_apart_and_every_row_is_drawn(tmp_path):
    rows = []
    for label, shift in (("shipped", 0.0), ("candidate", 0.1)):
        val = _result(tmp_path / f"val_{label}.json", {"sample_1": (0.6 + shift, 0.10, 100.0),
                                                        "sample_2": (0.4 + shift, 0.20, 300.0)})
        real = _result(tmp_path / f"real_{label}.json", {"av2_log": (0.45, 0.08 + shift, 50.0)}, swing=0.01)
        rows += ["--row", f"{label}={val},{real}"]
    out = tmp_path / "frontier.json"
    assert cut_frontier.main([*rows, "--val-name", "av2 val", "--out", str(out)]) == 0
    pts = json.loads(out.read_text())["points"]
    val = pts["av2 val"]
    assert [round(x, 6) for x in val["shipped"]] == [50.0, 15.0, 200.0, 0.0, 2]
    assert [round(x, 6) for x in val["candidate"]] == [60.0, 15.0, 200.0, 0.0, 2]
    # two samples 1 point either side of 18 %: standard deviation 1.414, over sqrt(2) -> 1.0
    assert [round(x, 6) for x in pts["av2_log"]["candidate"]] == [45.0, 18.0, 50.0, 1.0, 2]
    md = out.with_suffix(".md").read_text()
    assert "| candidate | 60.0 / 15.0 ± 0.0 / 200 / 2 | 45.0 / 18.0 ± 1.0 / 50 / 2 |" in md
    assert out.with_suffix(".png").stat().st_size > 10_000


def test_the_standard_error_of_averaged_val_sweeps_and_results_without_samples(tmp_path):
    import pytest

    # two sweeps with standard errors 1 and 2 points: their mean's is sqrt(1 + 4) / 2
    rows = {"w": {"val/a": {"cut_2": {"recall": 0.5, "above_empty_share": 0.1, "generated_above": 10.0, "k": 3,
                                      "above_empty_sem": 0.01}},
                  "val/b": {"cut_2": {"recall": 0.5, "above_empty_share": 0.1, "generated_above": 10.0, "k": 6,
                                      "above_empty_sem": 0.02}},
                  "log": {"cut_2": {"recall": 0.4, "above_empty_share": 0.2, "generated_above": 5.0, "k": 1,
                                    "above_empty_sem": None}}}}
    pts = cut_frontier.points(rows, "val")
    assert pts["val"]["w"][3] == pytest.approx(5 ** 0.5 / 2) and pts["val"]["w"][4] == 3
    assert pts["log"]["w"][3] is None  # one sample: no spread to measure
    assert "| w | 50.0 / 10.0 ± 1.1 / 10 / 3 | 40.0 / 20.0 / 5 / 1 |" in cut_frontier.table(pts)


def test_a_row_without_two_files_is_refused(tmp_path, capsys):
    import pytest

    with pytest.raises(SystemExit) as e:
        cut_frontier.main(["--row", "shipped=only_one.json", "--out", str(tmp_path / "f.json")])
    assert e.value.code == 2 and "expected LABEL=VAL.json,REAL.json" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        cut_frontier.main(["--row", "shipped=,", "--out", str(tmp_path / "f.json")])
    assert e.value.code == 2 and "not both" in capsys.readouterr().err


def _run(path: Path, seed: int, shares: list[float], inputs=("av2_log",), t1=None, digest="ab12", file="w.pt") -> str:
    """An eval-real JSON of len(shares) samples from `seed` on: each sample's recall 0.4 + its share."""
    per = [{"recall": 0.4 + a, "generated_above": 100.0 * (i + 1), "above_empty_share": a} for i, a in enumerate(shares)]
    whole = [{"empty_share": 0.05} for _ in shares]
    doc = {"config": {"cuts": [2.0], "samples": len(shares), "seed": seed, "threads": 1, "t1": t1,
                      "weights": {"coarse": file}, "weights_sha256": {"coarse": digest}},
           "inputs": {name: {"cases": {"full": {"rows": {"hgca": {"per_sample": whole, "summary": {}}}},
                                       "cut_2": {"rows": {"hgca": {"per_sample": per, "summary": {}}}}}}
                      for name in inputs}}
    path.write_text(json.dumps(doc))
    return str(path)


def test_runs_of_other_seeds_pool_into_one_score_and_refuse_what_would_not_be_one(tmp_path):
    import pytest

    from keep_sweep import pooled

    a = _run(tmp_path / "a.json", 0, [0.10, 0.12])
    b = _run(tmp_path / "b.json", 2, [0.14, 0.16])
    both = pooled(f"{a}+{b}")
    row = both["inputs"]["av2_log"]["cases"]["cut_2"]["rows"]["hgca"]
    assert row["k"] == 4 and both["config"]["samples"] == 4 and both["config"]["seeds"] == [[0, 2], [2, 4]]
    assert row["summary"]["above_empty_share"]["mean"] == pytest.approx(0.13)
    assert row["summary"]["recall"]["min"] == pytest.approx(0.50) and row["summary"]["recall"]["max"] == pytest.approx(0.56)
    # the frontier reads the pooled row: mean 13 %, standard error of four samples 0.02 apart: 2.582 / 2 = 1.291
    pts = cut_frontier.points(cut_frontier.known_rows([f"w={a}+{b},{a}+{b}"]))
    assert pts["av2_log"]["w"][1] == pytest.approx(13.0) and pts["av2_log"]["w"][4] == 4
    assert pts["av2_log"]["w"][3] == pytest.approx(100 * (0.02 * (5 / 3) ** 0.5) / 2)
    assert pooled(a) == json.loads(Path(a).read_text())   # one file reads as it is
    with pytest.raises(ValueError, match="overlap"):
        pooled(f"{a}+{_run(tmp_path / 'c.json', 1, [0.2, 0.2])}")
    with pytest.raises(ValueError, match="cannot pool"):
        pooled(f"{a}+{_run(tmp_path / 'd.json', 2, [0.2, 0.2], t1=20)}")
    with pytest.raises(ValueError, match="cannot pool"):
        pooled(f"{a}+{_run(tmp_path / 'e.json', 2, [0.2, 0.2], inputs=('other_log',))}")
    with pytest.raises(ValueError, match="cannot pool"):   # other weights under the same name
        pooled(f"{a}+{_run(tmp_path / 'f.json', 2, [0.2, 0.2], digest='cd34')}")
    moved = pooled(f"{a}+{_run(tmp_path / 'g.json', 2, [0.2, 0.2], file='/elsewhere/w.pt')}")   # same weights
    assert moved["config"]["samples"] == 4


def test_rank_agreement_between_val_and_each_input_set():
    """Spearman over the rows: +1 where a set orders the weights as the val sweeps do, -1 reversed; none below 4
    rows (too few to rank) and none for the val set itself."""
    import pytest

    val = {f"w{i}": (50.0 + i, 5.0 + i, 0.0, None, 3) for i in range(5)}
    same = {f"w{i}": (40.0 + 2 * i, 9.0 + 0.5 * i, 0.0, None, 6) for i in range(5)}
    reversed_share = {f"w{i}": (40.0 + i, 12.0 - i, 0.0, None, 6) for i in range(5)}
    few = {f"w{i}": (40.0 + i, 9.0, 0.0, None, 6) for i in range(3)}
    ranks = cut_frontier.agreement({"val": val, "log_a": same, "log_b": reversed_share, "log_c": few}, "val")
    assert set(ranks) == {"log_a", "log_b"}
    assert ranks["log_a"] == pytest.approx((1.0, 1.0, 5))
    assert ranks["log_b"] == pytest.approx((1.0, -1.0, 5))


def test_a_row_scored_on_the_real_logs_only_is_drawn_and_tabled_there(tmp_path):
    val = _result(tmp_path / "val.json", {"sample_1": (0.6, 0.10, 100.0)})
    real = _result(tmp_path / "real.json", {"av2_log": (0.45, 0.08, 50.0)})
    other = _result(tmp_path / "real_b.json", {"av2_log": (0.50, 0.07, 60.0)})
    out = tmp_path / "f.json"
    assert cut_frontier.main(["--row", f"ref={val},{real}", "--row", f"b=,{other}", "--out", str(out)]) == 0
    pts = json.loads(out.read_text())["points"]
    assert set(pts["synthetic val sweeps"]) == {"ref"} and set(pts["av2_log"]) == {"ref", "b"}
    assert "| b | - | 50.0 / 7.0 ± 0.0 / 60 / 2 |" in out.with_suffix(".md").read_text()


def test_a_row_screened_on_the_val_sweeps_only_is_drawn_there_and_ranked_nowhere_else(tmp_path):
    rows, outs = [], {}
    for i in range(4):
        val = _result(tmp_path / f"val{i}.json", {"sample_1": (0.5 + 0.05 * i, 0.05 + 0.01 * i, 100.0)})
        real = _result(tmp_path / f"real{i}.json", {"av2_log": (0.40 + 0.05 * i, 0.08 + 0.01 * i, 50.0)})
        rows += ["--row", f"w{i}={val},{real}"]
    screened = _result(tmp_path / "val_s.json", {"sample_1": (0.9, 0.01, 120.0)})
    out = tmp_path / "f.json"
    assert cut_frontier.main([*rows, "--row", f"s={screened},", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert "s" in doc["points"]["synthetic val sweeps"] and "s" not in doc["points"]["av2_log"]
    assert doc["rank_agreement"]["av2_log"][2] == 4          # ranked over the rows both sets hold
    assert "| s | 90.0 / 1.0 ± 0.0 / 120 / 2 | - |" in out.with_suffix(".md").read_text()


def test_an_out_that_is_not_json_or_is_an_input_is_refused_before_anything_is_written(tmp_path, capsys):
    import pytest

    val = _result(tmp_path / "val.json", {"sample_1": (0.6, 0.10, 100.0)})
    real = _result(tmp_path / "real.json", {"av2_log": (0.45, 0.08, 50.0)})
    before = Path(real).read_text()
    for out, said in ((tmp_path / "frontier", "name a .json file"), (Path(real), "would overwrite")):
        with pytest.raises(SystemExit) as e:
            cut_frontier.main(["--row", f"ref={val},{real}", "--out", str(out)])
        assert e.value.code == 2 and said in capsys.readouterr().err
    assert Path(real).read_text() == before and not (tmp_path / "frontier").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["real.json", "val.json"]


def test_a_sample_that_grew_nothing_above_the_cut_has_no_share_to_average(tmp_path):
    """Session 37: one of WE's 48 val completions grew no cell above the cut (share None in its results file):
    the row's standard error is over the samples that have a share, and k still counts every sample."""
    path = tmp_path / "val.json"
    _result(path, {"sample_1": (0.1, 0.25, 10.0)}, swing=0.01)
    doc = json.loads(path.read_text())
    doc["inputs"]["sample_1"]["cases"]["cut_2"]["rows"]["hgca"]["per_sample"].append({"above_empty_share": None})
    path.write_text(json.dumps(doc))
    out = tmp_path / "frontier.json"
    assert cut_frontier.main(["--row", f"w={path},", "--val-name", "val", "--out", str(out)]) == 0
    rec, share, cells, sem, k = json.loads(out.read_text())["points"]["val"]["w"]
    assert (round(share, 6), round(sem, 6), k) == (25.0, 1.0, 3)

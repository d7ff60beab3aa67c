"""benchmarks/completion_ab.py: interleaved A/B of completion time (allocator, or an earlier revision)."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import completion_ab  # noqa: E402
from completion_ab import Side  # noqa: E402

MACHINE = {"cpu": "x", "cores": 2, "torch": "t", "date": "d"}   # what `hardware.machine()` gives a table


def test_sides_alternate_so_each_runs_first_as_often_as_second():
    a, b = Side("a", Path(".")), Side("b", Path("."))
    order = [s.name for s in completion_ab.alternate((a, b), 4)]
    assert order == ["a", "b", "b", "a", "a", "b", "b", "a"]


def test_table_reports_medians_and_marks_what_a_side_did_not_measure():
    runs = [{"side": "old", "seconds": 16.0, "peak_rss_gib": 1.7, "stages_s": {"coarse": 14.0}},
            {"side": "new", "seconds": 12.0, "minor_faults": 300_000, "peak_rss_gib": 1.6, "stages_s": {"coarse": 10.0}},
            {"side": "new", "seconds": 14.0, "minor_faults": 320_000, "peak_rss_gib": 1.5, "stages_s": {"coarse": 11.0}},
            {"side": "old", "seconds": 18.0, "peak_rss_gib": 1.8, "stages_s": {"coarse": 15.0}}]
    block = {"runs": runs, "summary": completion_ab.summary(runs, ("old", "new"))}
    s = block["summary"]
    assert s["old"]["median_s"] == 17.0 and s["new"]["median_s"] == 13.0 and s["new"]["median_faults"] == 310_000
    assert "median_faults" not in s["old"] and s["old"]["max_rss_gib"] == 1.8
    text = completion_ab.table({"machine": MACHINE, "title": "t", "blocks": {"completion": block}})
    assert "| old | 2 | 17.00 | 16.00 | - | 1.75 / 1.80 | coarse 14.50 |" in text
    assert "| new | 2 | 13.00 | 12.00 | 310,000 | 1.55 / 1.60 | coarse 10.50 |" in text
    assert "Median difference (new - old): -4.00 s" in text


def test_unknown_revision_is_refused_before_any_run(tmp_path, monkeypatch):
    monkeypatch.setattr(completion_ab, "completion_run", lambda *a: pytest.fail("ran a completion"))
    with pytest.raises(SystemExit, match="not a commit"):
        completion_ab.main(["base", "no-such-revision-xyz", "--out", "test_ab_never_written"])
    assert not list((completion_ab.REPO / "benchmarks" / "results").glob("test_ab_never_written*"))


def test_table_says_whether_the_sides_made_the_same_mesh():
    runs = [{"side": "a", "seconds": 10.0, "mesh_sha256": "ab" * 32},
            {"side": "b", "seconds": 9.0, "mesh_sha256": "ab" * 32}]
    block = {"runs": runs, "summary": completion_ab.summary(runs, ("a", "b"))}
    head = {"machine": MACHINE, "title": "t"}
    assert "Output meshes: 1 distinct over 2 runs (sha256 abababababab)." in completion_ab.table(
        {**head, "blocks": {"c": block}})
    runs[1]["mesh_sha256"] = "cd" * 32
    assert "Output meshes: 2 distinct over 2 runs" in completion_ab.table({**head, "blocks": {"c": block}})


def test_input_and_width_are_one_or_the_other(monkeypatch):
    monkeypatch.setattr(completion_ab, "completion_run", lambda *a: pytest.fail("ran a completion"))
    with pytest.raises(SystemExit):
        completion_ab.main(["allocator", "--width", "60", "--input", "scan.laz", "--out", "test_ab_never_written"])

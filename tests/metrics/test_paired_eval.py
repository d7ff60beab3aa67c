"""benchmarks/paired_eval.py: the per-scene paired difference of two evaluations, its standard error and the
count of scenes lowered, and the refusal to pair evaluations of different scenes."""
import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import paired_eval  # noqa: E402


def _eval(iou, files=("a", "b", "c")):
    per = {"iou": list(iou), "resim_min": [0.1] * len(iou), "street_cd_min": [0.2] * len(iou)}
    return {"files": list(files), "rows": {paired_eval.ROW: {"per_scene": per}}}


def test_the_paired_difference_is_per_scene_with_its_standard_error():
    r = paired_eval.paired(_eval([0.50, 0.70, 0.62]), _eval([0.52, 0.71, 0.60]))["iou"]
    # differences -2, -1, +2 points: mean -1/3, sample sd sqrt(13/3), se sd / sqrt(3)
    assert r["diff"] == pytest.approx(-1 / 3) and r["se"] == pytest.approx((13 / 3) ** 0.5 / 3 ** 0.5)
    assert r["lower"] == 2 and r["n"] == 3 and r["mean"] == pytest.approx(60.6667, abs=1e-3)
    assert paired_eval.paired(_eval([0.5] * 3), _eval([0.5] * 3))["resim_min"]["diff"] == 0


def test_evaluations_of_different_scenes_are_not_paired(tmp_path, capsys):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps(_eval([0.5, 0.6, 0.7])))
    b.write_text(json.dumps(_eval([0.5, 0.6, 0.7], files=("a", "b", "d"))))
    with pytest.raises(SystemExit, match="different scenes"):
        paired_eval.main([str(a), "--base", str(b)])
    assert paired_eval.main([str(a), "--base", str(a)]) == 0
    assert "iou 60.00 (diff +0.00 +- 0.00, 0/3 lower)" in capsys.readouterr().out

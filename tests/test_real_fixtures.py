"""The real LiDAR fixtures live in the repository (tests/data/real): tests that need them skip on a checkout
without them, but fail under CI (`CI` set), where a missing folder means the real-file tests silently stopped
running."""
import subprocess
import sys
from pathlib import Path

import pytest

from hgca_testdata import REAL_FIXTURES, in_ci, require_real

REPO = Path(__file__).resolve().parents[1]
# Every file the tests and `hgca eval-real` read, with the licence and notice files that must travel with them
EXPECTED = (
    "README.md", "licenses/LICENSE_laspy.txt", "nuscenes_lidar_top_1532402927647951.pcd.bin", "simple.las", "simple.laz",
    "simple1_4.las", "plane.laz", "simple.copc.laz", "autzen_trim.laz",
    "av2/NOTICE_av2-api.txt", "av2/LICENSE_av2-api_code.txt",
    "av2/7fab2350-7eaf-3b7e-a39d-6937a4c1bede/city_SE3_egovehicle.feather",
    "av2/7fab2350-7eaf-3b7e-a39d-6937a4c1bede/calibration/egovehicle_SE3_sensor.feather",
    "av2/7fab2350-7eaf-3b7e-a39d-6937a4c1bede/sensors/lidar/315966265259836000.feather",
    "av2/7fab2350-7eaf-3b7e-a39d-6937a4c1bede/sensors/lidar/315966265360032000.feather",
    "av2/adcf7d18-0510-35b0-a2fa-b4cea13a6d76/city_SE3_egovehicle.feather",
    "av2/adcf7d18-0510-35b0-a2fa-b4cea13a6d76/sensors/lidar/315973157959879000.feather",
)


@pytest.mark.parametrize("value, ci", [("true", True), ("1", True), ("", False), ("false", False), ("0", False)])
def test_ci_variable(monkeypatch, value, ci):
    monkeypatch.setenv("CI", value)
    assert in_ci() is ci


def test_missing_fixture_fails_under_ci_and_skips_otherwise(monkeypatch, tmp_path):
    missing = tmp_path / "nope.laz"
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="nope.laz.*CI is set"):
        require_real(missing)
    monkeypatch.delenv("CI")
    with pytest.raises(pytest.skip.Exception, match="nope.laz"):
        require_real(missing)
    assert require_real(tmp_path) == tmp_path


def test_the_real_folder_is_inside_the_repository():
    assert REAL_FIXTURES == REPO / "tests" / "data" / "real"
    assert require_real() == REAL_FIXTURES


@pytest.mark.parametrize("name", EXPECTED)
def test_every_fixture_and_its_licence_is_tracked(name):
    """On disk and in git: a file present only in one working tree would pass here and be missing from a clone."""
    path = require_real(REAL_FIXTURES / name)
    assert path.stat().st_size > 0
    tracked = subprocess.run(["git", "ls-files", "--error-unmatch", str(path.relative_to(REPO))], cwd=REPO,
                             capture_output=True, text=True)
    if tracked.returncode != 0 and "not a git repository" in tracked.stderr:
        pytest.skip("not a git checkout")
    assert tracked.returncode == 0, f"{name} is not tracked by git: {tracked.stderr.strip()}"


def test_the_fixtures_readme_names_each_licence():
    text = (REAL_FIXTURES / "README.md").read_text()
    for needle in ("CC BY-NC-SA 4.0", "MIT", "BSD", "NOTICE_av2-api.txt", "LICENSE_laspy.txt"):
        assert needle in text


def test_eval_real_defaults_to_the_repository_fixtures(tmp_path):
    """`hgca eval-real` finds the fixtures from any working folder, not only from the repository root."""
    code = ("import argparse; from hgca_core.commands import eval_real as e; p = argparse.ArgumentParser(); "
            "e.add_arguments(p); print(p.parse_args(['--out', 'r.json']).real_dir)")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, check=True)
    assert Path(out.stdout.strip()).resolve() == REAL_FIXTURES
    from hgca_core.commands.eval_real import default_items

    items = default_items(REAL_FIXTURES)
    assert len(items) == 3
    for item in items:
        assert Path(item["path"]).exists(), item
        assert item["calibration"] is None or Path(item["calibration"]).is_file(), item


def test_no_default_path_outside_the_repository():
    """No tracked file points at a fixtures folder beside the repository. Results JSON keep the paths they were
    measured from (a record, not a default), so benchmarks/results is left out."""
    hits = subprocess.run(["git", "grep", "-nE", r"\.\./shared|shared/(fixtures|DESIGN)", "--", ".",
                           ":!tests/data/real", ":!benchmarks/results", ":!tests/test_real_fixtures.py"],
                          cwd=REPO, capture_output=True, text=True)
    if hits.returncode not in (0, 1):
        pytest.skip("not a git checkout")
    assert hits.stdout == ""

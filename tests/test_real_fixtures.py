"""Tests that need ../shared/fixtures/real skip on a machine without it, but fail under CI (`CI` set), where a
missing folder means the real-file tests silently stopped running."""
import pytest

from hgca_testdata import REAL_FIXTURES, in_ci, require_real


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


def test_the_real_folder_is_where_ci_expects_it():
    """Beside the repository, as ../shared/fixtures/real (CI clones the repo with ../shared beside it)."""
    assert REAL_FIXTURES.parts[-3:] == ("shared", "fixtures", "real")
    assert REAL_FIXTURES.parent.parent.parent == __import__("pathlib").Path(__file__).resolve().parents[2]
    if REAL_FIXTURES.is_dir() or in_ci():
        assert any(require_real().iterdir())

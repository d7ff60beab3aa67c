"""The Blender add-on's settings are the core's by construction: the extension build writes
`hgca_core.config.addon_schema()` into the add-on (`core_settings.json`), and the panel's properties, the batch
options and every job's command line are made from it (`hgca_blender/settings.py`). These tests hold the build
to the schema and the add-on's sources to using it instead of numbers of their own; tests/blender checks the
registered properties themselves."""
from __future__ import annotations

import ast
import json
from pathlib import Path

import pytest

from hgca_blender import build_extension
from hgca_core.config import CLI_FLAGS, addon_limits, addon_schema

ADDON = Path(__file__).resolve().parents[1] / "hgca_blender"


def test_the_staged_addon_carries_the_cores_schema(tmp_path: Path) -> None:
    staged = build_extension.stage(tmp_path / "hgca")
    assert json.loads((staged / "core_settings.json").read_text()) == json.loads(json.dumps(addon_schema()))


def _keyword_sources(path: Path, group: str) -> dict[str, dict[str, str]]:
    """Each annotated property of the PropertyGroup `group`: its keywords as source text."""
    tree = ast.parse(path.read_text())
    cls = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == group)
    return {n.target.id: {k.arg: ast.unparse(k.value) for k in n.annotation.keywords}
            for n in cls.body if isinstance(n, ast.AnnAssign) and isinstance(n.annotation, ast.Call)}


@pytest.mark.parametrize("name", sorted(addon_limits()))
def test_a_panel_setting_takes_its_default_and_bounds_from_the_schema(name: str) -> None:
    props = _keyword_sources(ADDON / "properties.py", "HGCA_PG_scene")
    keywords = props[name]
    assert f"core.default('{name}')" in keywords["default"], (name, keywords)
    core = addon_limits()[name]
    for bound in ("min", "max"):
        if core.get(bound) is not None and name != "max_faces":
            assert bound in keywords and f"'{name}'" in keywords[bound], (name, bound, keywords)


def test_every_setting_the_addon_shows_has_a_cli_flag() -> None:
    assert set(addon_limits()) == set(CLI_FLAGS)


def test_jobs_build_their_command_lines_through_one_function() -> None:
    """No job types the core's flags itself: completion and drive command lines come from settings.core_args."""
    for module in ("jobs/completion.py", "jobs/drive_job.py"):
        text = (ADDON / module).read_text()
        assert "settings.core_args(" in text
        for flag in ("--samples", "--seed", "--stage", "--quality", "--t1", "--t2", "--max-faces", "--workers"):
            assert f'"{flag}"' not in text, (module, flag)


def test_the_panels_region_size_is_the_cores() -> None:
    """The panel's default region box is the core's default region (`config.REGION_SIZE`, carried by the schema),
    not a copy of its numbers."""
    from hgca_blender import settings
    from hgca_core.config import REGION_SIZE
    from hgca_core.geometry.region import DEFAULT_SIZE

    assert settings.REGION_SIZE == tuple(REGION_SIZE) == tuple(DEFAULT_SIZE)
    props = _keyword_sources(ADDON / "properties.py", "HGCA_PG_scene")
    assert props["region_size"]["default"] == "core.REGION_SIZE"
    assert "38.4" not in (ADDON / "properties.py").read_text() + (ADDON / "scene" / "region.py").read_text()

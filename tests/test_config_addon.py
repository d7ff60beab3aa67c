"""The Blender add-on's settings follow the core's config: it runs the core as a subprocess and cannot import
it, so its property defaults are held equal to `CompletionConfig` / `DriveConfig`'s (`config.addon_limits`) and
its bounds inside the core's (the panel never offers what the core refuses)."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

from hgca_core.config import addon_limits

PROPERTIES = Path(__file__).resolve().parents[1] / "hgca_blender" / "properties.py"


def _properties() -> dict[str, dict]:
    """Each annotated property of the scene's PropertyGroup: its keyword arguments, constants resolved."""
    tree = ast.parse(PROPERTIES.read_text())
    constants = {t.id: ast.literal_eval(n.value) for n in tree.body if isinstance(n, ast.Assign)
                 for t in n.targets if isinstance(t, ast.Name) and isinstance(n.value, ast.Constant)}
    group = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "HGCA_PG_scene")
    out = {}
    for node in group.body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.annotation, ast.Call):
            kw = {}
            for k in node.annotation.keywords:
                if isinstance(k.value, ast.Name) and k.value.id in constants:
                    kw[k.arg] = constants[k.value.id]
                elif k.arg in ("default", "min", "max"):
                    try:
                        kw[k.arg] = ast.literal_eval(k.value)
                    except ValueError:          # a name imported from another module (the region's size)
                        kw[k.arg] = ast.unparse(k.value)
                elif k.arg == "items":
                    kw["choices"] = [ast.literal_eval(e.elts[0]) for e in k.value.elts]
            out[node.target.id] = kw
    return out


@pytest.mark.parametrize("name", sorted(addon_limits()))
def test_an_addon_setting_has_the_cores_default_and_stays_in_its_bounds(name):
    core, prop = addon_limits()[name], _properties()[name]
    assert prop.get("default") == core["default"], (name, prop, core)
    if "choices" in core:
        assert set(prop["choices"]) <= set(core["choices"])
    if core.get("min") is not None:
        assert prop.get("min") is not None and prop["min"] >= core["min"], (name, prop, core)
    if core.get("max") is not None:
        assert prop.get("max", 2**31 - 1) <= core["max"], (name, prop, core)

"""Dependency directions and the one weights module, read from the source (every import, also those inside
functions): geometry (keys, voxels, regions, the voxel mesher) imports no other hgca_core layer; models never
import training, commands or the benchmark; training never imports the benchmark
or the commands; only hgca_core/models/weights.py calls torch.load / torch.save, and only with weights_only=True."""
import ast
from pathlib import Path

import pytest

CORE = Path(__file__).resolve().parents[1] / "hgca_core"

FORBIDDEN = {
    "geometry": ("hgca_core.nn", "hgca_core.models", "hgca_core.training", "hgca_core.commands", "hgca_core.pipeline",
                 "hgca_core.bench", "hgca_core.metrics", "hgca_core.synth", "hgca_core.meshing"),
    "nn": ("hgca_core.models", "hgca_core.training", "hgca_core.commands", "hgca_core.pipeline", "hgca_core.bench"),
    "models": ("hgca_core.training", "hgca_core.commands", "hgca_core.pipeline", "hgca_core.bench"),
    "training": ("hgca_core.bench", "hgca_core.commands", "hgca_core.pipeline"),
    "tiling": ("hgca_core.bench", "hgca_core.commands", "hgca_core.training"),
}


def imported_modules(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names |= {f"{node.module}.{a.name}" for a in node.names}
    return names


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_imports_point_one_way(package):
    files = sorted((CORE / package).glob("*.py"))
    assert files
    bad = {f"{f.relative_to(CORE)} imports {m}" for f in files for m in imported_modules(f)
           for prefix in FORBIDDEN[package] if m == prefix or m.startswith(prefix + ".")}
    assert not bad, sorted(bad)


def _torch_calls(tree: ast.AST, name: str) -> list[ast.Call]:
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute)
            and n.func.attr == name and isinstance(n.func.value, ast.Name) and n.func.value.id == "torch"]


def test_only_the_weights_module_loads_and_saves_with_torch():
    users = {}
    for path in sorted(CORE.rglob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        for name in ("load", "save"):
            if _torch_calls(tree, name):
                users.setdefault(name, []).append(str(path.relative_to(CORE)))
    assert users == {"load": ["models/weights.py"], "save": ["models/weights.py"]}
    loads = _torch_calls(ast.parse((CORE / "models" / "weights.py").read_text()), "load")
    for call in loads:
        kw = {k.arg: k.value for k in call.keywords}
        assert isinstance(kw.get("weights_only"), ast.Constant) and kw["weights_only"].value is True

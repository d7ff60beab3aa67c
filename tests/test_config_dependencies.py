"""Dependencies declared where they are used: every runtime dependency in pyproject.toml is imported by the core
(or is a named backend another dependency loads), and every third-party module the core imports is declared."""
from __future__ import annotations

import ast
import re
import sys
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# distribution -> the module the core imports; None: a backend another dependency loads by itself
MODULE = {"torch": "torch", "numpy": "numpy", "scipy": "scipy", "trimesh": "trimesh", "fast-simplification":
          "fast_simplification", "pykdtree": "pykdtree", "laspy": "laspy", "plyfile": "plyfile",
          "matplotlib": "matplotlib", "tqdm": "tqdm", "psutil": "psutil", "open3d-cpu": "open3d",
          "pyarrow": "pyarrow", "ray": "ray",
          "embreex": None,   # trimesh's ray casting (synthetic LiDAR, ray-hit visibility)
          "rtree": None,     # trimesh's spatial index
          "lazrs": "lazrs", "pillow": "PIL", "scikit-image": "skimage",
          "rosbags": "rosbags", "pye57": "pye57", "kiss-icp": "kiss_icp"}


def _name(requirement: str) -> str:
    return re.match(r"[A-Za-z0-9_.-]+", requirement).group(0).lower()


def _project() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())["project"]


def _core_imports() -> set[str]:
    names = set()
    for f in (REPO / "hgca_core").rglob("*.py"):
        for node in ast.walk(ast.parse(f.read_text(), str(f))):
            if isinstance(node, ast.Import):
                names |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names.add(node.module.split(".")[0])
    return names - set(sys.stdlib_module_names) - {"hgca_core"}


def test_every_runtime_dependency_is_used_by_the_core():
    used = _core_imports()
    runtime = [_name(r) for r in _project()["dependencies"]]
    unknown = [d for d in runtime if d not in MODULE]
    assert not unknown, f"map these to their module in MODULE: {unknown}"
    unused = [d for d in runtime if MODULE[d] is not None and MODULE[d] not in used]
    assert not unused, f"runtime dependencies the core never imports (move them to an extra): {unused}"


def test_every_module_the_core_imports_is_declared():
    project = _project()
    declared = {_name(r) for r in project["dependencies"]}
    declared |= {_name(r) for extra in project["optional-dependencies"].values() for r in extra}
    modules = {MODULE[d] for d in declared if MODULE.get(d)}
    assert _core_imports() <= modules, sorted(_core_imports() - modules)

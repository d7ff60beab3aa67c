"""Dependency directions and the one weights module, read from the source (every import, also those inside
functions). The architecture's layers (docs/architecture.md): `commands` -> `pipeline` / `tiling` -> `models` ->
`nn` -> `geometry`; meshing is called by the pipeline (and training's validation), never by models; `training` and
`metrics` use `models`, never the reverse; no two modules import each other, even through a function-level import.
Only hgca_core/models/weights.py calls torch.load / torch.save, and only with weights_only=True.
Tests never import benchmarks/; benchmarks import of tests/ only the shared builders (tests/builders.py and co)."""
import ast
import importlib
import importlib.util
import re
from pathlib import Path

import pytest

CORE = Path(__file__).resolve().parents[1] / "hgca_core"

UTIL = {"errors", "hardware", "interrupt", "progress"}   # what any layer may use
LOW = UTIL | {"io", "geometry"}
# each layer (a top-level package or module of hgca_core) and the layers it may import; "hgca_core" is the package's
# own API (`hgca_core.complete`), for the front ends only
ALLOWED = {
    "errors": set(),
    "config": {"errors", "nn"},   # nn.precision's names only (test_config_is_light)
    "io": {"errors", "geometry"},   # geometry.nearest: the odometry's registration checks
    "geometry": UTIL | {"config"},   # the default region's size (config.REGION_SIZE)
    "nn": UTIL | {"geometry"},
    "models": LOW | {"config", "nn"},   # config: the bounds a weights file is checked against (MAX_STEPS)
    "meshing": LOW,
    "dataset": {"errors", "io", "geometry", "config"},   # the sample files' format: no simulator, no training
    "synth": LOW | {"dataset"},
    "render": LOW,
    "metrics": LOW | {"config", "dataset", "nn", "models", "meshing", "pipeline", "render", "synth"},
    "training": LOW | {"config", "dataset", "nn", "models", "meshing", "metrics", "synth"},
    "pipeline": LOW | {"config", "nn", "models", "meshing"},
    "tiling": LOW | {"config", "nn", "models", "meshing", "pipeline"},
}
FRONT_ENDS = {"commands", "cli"}   # above every layer; nothing in the core imports them


def _modules() -> dict[str, Path]:
    out = {}
    for f in sorted(CORE.rglob("*.py")):
        parts = ("hgca_core", *f.relative_to(CORE).with_suffix("").parts)
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = f
    return out


MODULES = _modules()


def imported_modules(path: Path) -> set[str]:
    """The hgca_core modules a file imports anywhere in it (`from hgca_core import interrupt` names the module)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            subs = {f"{node.module}.{a.name}" for a in node.names}
            names |= subs & set(MODULES) or {node.module}
    return {n for n in names if n in MODULES}


def layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "hgca_core"


@pytest.mark.parametrize("name", sorted(ALLOWED))
def test_each_layer_imports_only_the_layers_below_it(name):
    files = [(m, f) for m, f in MODULES.items() if layer(m) == name]
    assert files, name
    bad = sorted(f"{f.relative_to(CORE)} imports {d}" for m, f in files for d in imported_modules(f)
                 if layer(d) != name and layer(d) not in ALLOWED[name])
    assert not bad, bad


def test_config_is_light():
    """The settings module is read while parsing arguments: from the core it imports errors and the precision
    names only, and no torch or numpy (a fresh interpreter would pay seconds for them)."""
    import subprocess
    import sys

    path = MODULES["hgca_core.config"]
    assert imported_modules(path) <= {"hgca_core.errors", "hgca_core.nn.precision"}, imported_modules(path)
    code = "import sys, hgca_core.config; print(sorted({'torch', 'numpy'} & set(sys.modules)))"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True).stdout.strip() == "[]"


def test_no_layer_imports_the_front_ends():
    bad = sorted(f"{f.relative_to(CORE)} imports {d}" for m, f in MODULES.items() if layer(m) not in FRONT_ENDS
                 for d in imported_modules(f) if layer(d) in FRONT_ENDS)
    assert not bad, bad


def test_meshing_is_called_by_the_pipeline_not_by_models():
    users = {layer(m) for m, f in MODULES.items() for d in imported_modules(f) if layer(d) == "meshing"}
    assert "pipeline" in users and "models" not in users


# The mesh step is one package, hgca_core/meshing/ (docs/architecture.md, step 6): these modules moved there from
# geometry/, and the old hgca_core/meshing.py's names live in its submodules; no alias keeps an old name alive.
MESH_MODULES = ("voxel_mesh", "udf_surface", "fairing", "mesh_clean", "parallel")
OLD_MESHING_NAMES = ("udf_grid", "udf_grid_points", "udf_surface_points", "project_to_zero", "UdfFn", "udf_mesh",
                     "observed_vertices", "MIN_AREA", "PINHOLE_EDGES", "finish_mesh", "OBSERVED_SPLIT", "decimate",
                     "interruptible", "DEFAULT_MAX_FACES")
OLD_MESH_TEXT = re.compile(r"(?<![\w.])(?:hgca_core\.)?geometry[./](?:" + "|".join(MESH_MODULES) + r")\b"
                           r"|hgca_core/meshing\.py"
                           r"|(?<![\w.])(?:hgca_core\.)?meshing\.(?:" + "|".join(OLD_MESHING_NAMES) + r")\b")


def test_the_mesh_modules_live_in_meshing_only():
    assert not (CORE / "meshing.py").exists()
    assert sorted(m for m in MESH_MODULES if (CORE / "geometry" / f"{m}.py").exists()) == []
    assert sorted(m for m in MESH_MODULES if not (CORE / "meshing" / f"{m}.py").is_file()) == []
    assert not set(OLD_MESHING_NAMES) & set(vars(importlib.import_module("hgca_core.meshing")))


def _old_mesh_imports(path: Path) -> list[str]:
    """The imports in a file of a moved module at its old place or of an old hgca_core.meshing name."""
    old_modules = {f"hgca_core.geometry.{m}" for m in MESH_MODULES}
    bad = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            bad += [a.name for a in node.names if a.name in old_modules]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module in old_modules:
                bad.append(node.module)
            elif node.module == "hgca_core.geometry":
                bad += [f"hgca_core.geometry.{a.name}" for a in node.names if a.name in MESH_MODULES]
            elif node.module == "hgca_core.meshing":
                bad += [f"hgca_core.meshing.{a.name}" for a in node.names if a.name in OLD_MESHING_NAMES]
    return bad


def _old_paths(old_imports, old_text: re.Pattern) -> list[str]:
    """What names a moved place: imports of it in every Python file of the repository (core, add-on, tests,
    benchmarks, scripts) by `old_imports(path)`, and `old_text` in the core's source and the docs."""
    files = [p for top in ("hgca_core", "hgca_blender", "tests", "benchmarks", "scripts")
             for p in sorted((REPO / top).rglob("*.py"))]
    assert len(files) > 100
    bad = [f"{p.relative_to(REPO)} imports {b}" for p in files for b in old_imports(p)]
    texts = sorted(CORE.rglob("*.py")) + sorted((REPO / "docs").rglob("*.md")) + [REPO / "README.md"]
    return bad + [f"{p.relative_to(REPO)}:{i} names {m.group(0)}" for p in texts
                  for i, line in enumerate(p.read_text().splitlines(), 1) for m in old_text.finditer(line)]


def test_nothing_imports_the_old_mesh_paths():
    """Every Python file of the repository (core, add-on, tests, benchmarks, scripts) imports the mesh step from
    hgca_core.meshing's submodules, and the core's source and the docs name it there."""
    assert not _old_paths(_old_mesh_imports, OLD_MESH_TEXT)


def test_the_old_mesh_names_are_caught():
    """The two checks above see each way of naming the old places."""
    assert OLD_MESH_TEXT.search("see `hgca_core.geometry.voxel_mesh`") and OLD_MESH_TEXT.search("geometry/fairing.py")
    assert OLD_MESH_TEXT.search("(`meshing.udf_mesh`)") and OLD_MESH_TEXT.search("hgca_core/meshing.py")
    assert not OLD_MESH_TEXT.search("`hgca_core.meshing.fine.udf_mesh` and meshing/voxel_mesh.py")


def test_old_mesh_imports_are_caught(tmp_path):
    f = tmp_path / "old.py"
    f.write_text("import hgca_core.geometry.udf_surface\nfrom hgca_core.geometry import fairing\n"
                 "from hgca_core.meshing import udf_mesh, mesh_clean\nfrom hgca_core.meshing.fine import udf_mesh\n")
    assert _old_mesh_imports(f) == ["hgca_core.geometry.udf_surface", "hgca_core.geometry.fairing",
                                    "hgca_core.meshing.udf_mesh"]


# The dataset's files have one home, hgca_core/dataset/ (docs/architecture.md): the sample format moved there from
# synth/dataset.py and training/data.py, the packed coarse format from training/; no alias keeps an old name alive.
MOVED_FORMAT = {"hgca_core.synth.dataset": ("SPLITS", "SPLIT_SPAN", "FORMAT_VERSION", "KEYS", "save_sample",
                                            "load_sample", "sample_path"),
                "hgca_core.training.data": ("split_files", "load_arrays")}
OLD_PACKED = ".".join(("hgca_core", "training", "packed"))   # spelt apart: a grep for the old path finds nothing
OLD_FORMAT_TEXT = re.compile(r"(?<![\w.])(?:hgca_core\.)?training[./]packed\b"
                             r"|(?<![\w.])(?:hgca_core\.)?synth[./]dataset\.(?:"
                             + "|".join(MOVED_FORMAT["hgca_core.synth.dataset"]) + r")\b"
                             r"|(?<![\w.])(?:hgca_core\.)?training[./]data\.(?:split_files|load_arrays)\b")


def test_the_dataset_format_lives_in_dataset_only():
    assert (CORE / "dataset" / "samples.py").is_file() and (CORE / "dataset" / "packed.py").is_file()
    assert not (CORE / "training" / "packed.py").exists() and importlib.util.find_spec(OLD_PACKED) is None
    samples = importlib.import_module("hgca_core.dataset.samples")
    assert [n for names in MOVED_FORMAT.values() for n in names if not hasattr(samples, n)] == []
    # synth.dataset holds none of them; training.data at most imports one from its home to use it
    synth = vars(importlib.import_module("hgca_core.synth.dataset"))
    assert not set(MOVED_FORMAT["hgca_core.synth.dataset"]) & set(synth)
    data = vars(importlib.import_module("hgca_core.training.data"))
    assert [n for n in MOVED_FORMAT["hgca_core.training.data"]
            if data.get(n, getattr(samples, n)) is not getattr(samples, n)] == []


def _dotted(node: ast.AST) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        base = _dotted(node.value)
        return f"{base}.{node.attr}" if base else None
    return None


def _old_format_imports(path: Path) -> list[str]:
    """The imports in a file of the old packed module or of a moved format name from its old module, and the uses of
    a moved name as an attribute of its old module (`from hgca_core.synth import dataset; dataset.load_sample`)."""
    tree = ast.parse(path.read_text(), str(path))
    aliases = {m: m for m in MOVED_FORMAT}   # local name -> old module
    bad = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            bad += [a.name for a in node.names if a.name == OLD_PACKED]
            aliases.update({a.asname: a.name for a in node.names if a.asname and a.name in MOVED_FORMAT})
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module == OLD_PACKED:
                bad.append(node.module)
            elif node.module in MOVED_FORMAT:
                bad += [f"{node.module}.{a.name}" for a in node.names if a.name in MOVED_FORMAT[node.module]]
            for a in node.names:
                full = f"{node.module}.{a.name}"
                if full == OLD_PACKED:
                    bad.append(full)
                elif full in MOVED_FORMAT:
                    aliases[a.asname or a.name] = full
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            module = aliases.get(_dotted(node.value) or "")
            if module and node.attr in MOVED_FORMAT[module]:
                bad.append(f"{module}.{node.attr}")
    return bad


def test_nothing_imports_the_old_dataset_format_paths():
    """Every Python file of the repository reads and writes the dataset's files through hgca_core.dataset, and the
    core's source and the docs name the format there."""
    assert not _old_paths(_old_format_imports, OLD_FORMAT_TEXT)


def test_old_dataset_format_paths_are_caught(tmp_path):
    f = tmp_path / "old.py"
    f.write_text(f"import {OLD_PACKED}\nfrom hgca_core.training import packed, data\n"
                 "from hgca_core.synth.dataset import Drive, load_sample\nfrom hgca_core.synth import dataset as ds\n"
                 "import hgca_core.training.data\nds.KEYS, ds.make_sample, data.grids, data.split_files\n"
                 "hgca_core.training.data.load_arrays\n")
    assert sorted(_old_format_imports(f)) == sorted([
        OLD_PACKED, OLD_PACKED, "hgca_core.synth.dataset.load_sample", "hgca_core.synth.dataset.KEYS",
        "hgca_core.training.data.split_files", "hgca_core.training.data.load_arrays"])
    assert OLD_FORMAT_TEXT.search("hgca_core/training/" + "packed.py")
    assert OLD_FORMAT_TEXT.search("`synth.dataset.KEYS`")
    assert OLD_FORMAT_TEXT.search("(`training.data.split_files`)")
    assert not OLD_FORMAT_TEXT.search("`hgca_core.dataset.packed`, synth/dataset.py, `synth.dataset.make_sample`")


def test_no_import_cycles_between_modules():
    """Tarjan's strongly connected components of the module import graph (function-level imports included)."""
    graph = {m: imported_modules(f) - {m} for m, f in MODULES.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    assert not cycles, cycles


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


def test_one_nearest_neighbour_backend():
    """Only geometry/nearest.py builds a k-d tree: a second backend would give other neighbours on ties."""
    import re
    pattern = re.compile(r"\b(cKDTree|KDTree|pykdtree|sklearn\.neighbors)\b")
    root = Path(__file__).resolve().parents[1] / "hgca_core"
    users = sorted(str(p.relative_to(root)) for p in root.rglob("*.py")
                   if p.name != "nearest.py" and any(pattern.search(line) and not line.lstrip().startswith("#")
                                                     for line in p.read_text().splitlines()))
    assert users == []


def test_only_the_front_ends_read_the_command_line():
    """The library takes plain values (configs, settings dataclasses), never an argparse namespace: no function
    outside `commands` and `cli` has a parameter named `args`, and none of them imports argparse."""
    found = []
    for name, path in MODULES.items():
        if layer(name) in FRONT_ENDS:
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                params = node.args.posonlyargs + node.args.args + node.args.kwonlyargs
                found += [f"{name}.{node.name}" for a in params if a.arg == "args"]
            elif isinstance(node, ast.Import) and any(a.name == "argparse" for a in node.names):
                found.append(f"{name} imports argparse")
    assert found == []


REPO = CORE.parent
SELF_FOLDER = "str(Path(__file__).resolve().parent)"   # a sys.path entry a benchmark may add: its own folder
TESTS_FOLDER = "str(TESTS)"   # and the one benchmarks/common.py adds: tests/, for the shared builders
# The modules of tests/ a benchmark may import: builders that import neither pytest nor any other test module.
SHARED_BUILDERS = {"builders", "meshing_reference", "hostile"}
# Tests about a benchmark script's own behaviour; they run it as a subprocess, never import it.
SCRIPT_TESTS = {"tests/drive/test_gpu_check.py", "tests/metrics/test_train_scaling.py"}


def _sys_path_edits(tree: ast.AST, text: str) -> list[str]:
    """The source of every value a file puts on sys.path (insert, append, extend, assignment, +=)."""
    def is_sys_path(n: ast.AST) -> bool:
        n = n.value if isinstance(n, ast.Subscript) else n
        return isinstance(n, ast.Attribute) and n.attr == "path" and isinstance(n.value, ast.Name) \
            and n.value.id == "sys"

    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and is_sys_path(node.func.value) \
                and node.func.attr in ("insert", "append", "extend", "__setitem__"):
            found += [ast.get_source_segment(text, a) for a in node.args[1 if node.func.attr == "insert" else 0:]]
        elif isinstance(node, (ast.Assign, ast.AugAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(is_sys_path(t) for t in targets):
                found.append(ast.get_source_segment(text, node.value))
    return found


def _imported(tree: ast.AST) -> list[str]:
    """Every absolute import's module name (`import a.b` -> a.b, `from a import b` -> a)."""
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.append(node.module)
    return names


def _code_strings(tree: ast.AST) -> list[str]:
    """The string constants of a module that are not docstrings."""
    docs = {id(n.body[0].value) for n in ast.walk(tree)
            if isinstance(n, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and n.body
            and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
    return [n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)
            and id(n) not in docs]


def test_tests_never_import_benchmarks():
    """Tests never import a benchmark script nor put benchmarks/ on sys.path (what both need lives in tests/); a test
    names a script only when it is about that script's own behaviour (SCRIPT_TESTS), and runs it as a subprocess."""
    bench = {p.stem for p in (REPO / "benchmarks").glob("*.py")}
    tests = REPO / "tests"
    own = {p.stem for p in tests.rglob("*.py")} | {p.name for p in tests.rglob("*") if p.is_dir()}
    bad = []
    for path in sorted(tests.rglob("*.py")):
        rel = str(path.relative_to(REPO))
        text = path.read_text()
        tree = ast.parse(text, rel)
        bad += [f"{rel} puts {v} on sys.path" for v in _sys_path_edits(tree, text) if "bench" in v.lower()]
        bad += [f"{rel} imports {n} from benchmarks/" for n in _imported(tree)
                if n.split(".")[0] in bench - own or n.split(".")[0] == "benchmarks"]
        scripts = sorted({s for s in _code_strings(tree) for b in bench if s == f"{b}.py" or s.endswith(f"benchmarks/{b}.py")})
        reads_them = path.name == "test_layering.py"   # this file reads the scripts' source, it runs none
        if scripts and not reads_them and (rel not in SCRIPT_TESTS or "subprocess" not in _imported(tree)):
            bad.append(f"{rel} names the benchmark script(s) {scripts} outside a subprocess test of that script")
    assert not bad, bad


def test_benchmarks_reach_into_tests_only_for_the_shared_builders():
    """Benchmarks import the installed package, their folder's scripts and, of tests/, only the shared builders
    (which import neither pytest nor another test module, so they run outside pytest); they put nothing on sys.path
    but their own folder and, in benchmarks/common.py, tests/."""
    bench = REPO / "benchmarks"
    tests = REPO / "tests"
    own = {p.stem for p in bench.glob("*.py")}
    in_tests = ({p.stem for p in tests.rglob("*.py")} | {p.parent.name for p in tests.rglob("__init__.py")}) - own
    bad = []
    for path in sorted(bench.glob("*.py")):
        text = path.read_text()
        tree = ast.parse(text, str(path))
        allowed = {SELF_FOLDER} | ({TESTS_FOLDER} if path.name == "common.py" else set())
        bad += [f"{path.name} puts {v} on sys.path" for v in _sys_path_edits(tree, text) if v not in allowed]
        bad += [f"{path.name} imports {n} from tests/" for n in _imported(tree)
                if (n.split(".")[0] == "tests" or n.split(".")[0] in in_tests) and n.split(".")[0] not in SHARED_BUILDERS]
    shared = [tests / "builders.py", tests / "meshing_reference.py", *sorted((tests / "hostile").glob("*.py"))]
    assert {p.stem if p.parent == tests else p.parent.name for p in shared} == SHARED_BUILDERS
    test_modules = {p.stem for p in tests.rglob("*.py")} - {"builders", "meshing_reference"}
    for path in shared:
        tree = ast.parse(path.read_text(), str(path))
        bad += [f"{path.relative_to(REPO)} imports {n}" for n in _imported(tree)
                if n.split(".")[0] in ({"pytest", "hgca_testdata", "conftest"} | test_modules)]
    assert not bad, bad


# Writing weights is training's (training/export.py); models/weights.py reads and checks them, so a completion, a
# drive or the add-on's Check never imports training code.
EXPORT_NAMES = ("save_weights", "half_state", "blend_files", "lineage", "load_into", "widened", "kind_of")


def test_weights_are_written_by_training_and_read_by_models():
    weights = importlib.import_module("hgca_core.models.weights")
    export = importlib.import_module("hgca_core.training.export")
    assert [n for n in EXPORT_NAMES if hasattr(weights, n)] == []
    assert [n for n in EXPORT_NAMES if not callable(getattr(export, n, None))] == []
    runtime = ("pipeline", "tiling", "files", "meshing", "models", "nn", "geometry", "io")
    users = sorted(m for m, f in MODULES.items() if layer(m) in runtime
                   for d in imported_modules(f) if layer(d) == "training")
    assert users == []

"""Shared helpers for tests on real bpy (imported by conftest.py and the test modules).

BLENDER_USER_RESOURCES must point at a private folder before `import bpy`, so the tests never read or
write the user's Blender configuration; this module sets it before bpy is imported anywhere.
"""
from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

if "bpy" in sys.modules and "BLENDER_USER_RESOURCES" not in os.environ:
    raise RuntimeError("bpy was imported before tests/blender could isolate its user folder")
os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="hgca_blender_user_"))

import bpy  # noqa: E402
import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
for _p in (REPO, REPO / "tests"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

from hgca_testdata import REAL_FIXTURES as FIXTURES, require_real  # noqa: E402

NUSCENES = FIXTURES / "nuscenes_lidar_top_1532402927647951.pcd.bin"
REPO_MODULE = "hgca_test"
ADDON = f"bl_ext.{REPO_MODULE}.hgca"
# The interpreter that runs hgca_core for the add-on: this one, or the one HGCA_PYTHON names (`make test-blender`
# runs these tests on bpy 4.2/4.5 from venvs that hold only bpy, numpy and pytest; the core runs from .venv).
CORE_PYTHON = os.environ.get("HGCA_PYTHON") or sys.executable
# A small region around the nuScenes sensor keeps a real completion to a few seconds on 2 cores.
SMALL_REGION = (0.0, 0.0, -0.5, 9.6, 9.6, 4.0, 0.0)


def workbench_pixels(tmp_path: Path, size: int, distance: float = 4.0) -> np.ndarray:
    """(size, size, 4) pixels of a Workbench render (the Solid view's renderer: flat light, colour = Attribute) from
    a camera `distance` m down -y looking along +y at the origin."""
    scene = bpy.context.scene
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.display.shading.light = "FLAT"
    scene.display.shading.color_type = "VERTEX"  # shown as "Attribute"
    scene.view_settings.view_transform = "Standard"
    scene.render.resolution_x = scene.render.resolution_y = size
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    cam.location, cam.rotation_euler = (0, -distance, 0), (np.pi / 2, 0, 0)
    scene.collection.objects.link(cam)
    scene.camera = cam
    scene.render.filepath = str(tmp_path / "solid.png")
    bpy.ops.render.render(write_still=True)
    image = bpy.data.images.load(scene.render.filepath)
    return np.array(image.pixels[:]).reshape(size, size, 4)


def ply_rgb(rows: list[tuple[float, float, float, int, int, int]]) -> str:
    """An ASCII PLY of points with 8-bit red, green, blue."""
    head = ["ply", "format ascii 1.0", f"element vertex {len(rows)}", *(f"property float {a}" for a in "xyz"),
            *(f"property uchar {c}" for c in ("red", "green", "blue")), "end_header"]
    return "\n".join(head + [" ".join(str(v) for v in row) for row in rows]) + "\n"


def require_fixture(path: Path) -> Path:
    """A real fixture file: skipped where missing, a failure under CI (`hgca_testdata.require_real`)."""
    return require_real(path)


def addon_module(name: str):
    """A submodule of the enabled add-on (e.g. "jobs"), as Blender loaded it."""
    return sys.modules[f"{ADDON}.{name}"]


def prefs():
    return bpy.context.preferences.addons[ADDON].preferences


def snapshot() -> dict:
    """Everything a job must not change: datablock names and every object's data and transform."""
    objects = {}
    for obj in bpy.data.objects:
        entry = {"matrix": np.array(obj.matrix_world).round(9).tolist(), "type": obj.type,
                 "collections": sorted(c.name for c in obj.users_collection)}
        if obj.type == "MESH":
            co = np.empty(len(obj.data.vertices) * 3, dtype=np.float32)
            obj.data.vertices.foreach_get("co", co)
            entry["co"] = co.tobytes()
            entry["attributes"] = sorted(a.name for a in obj.data.attributes)
        objects[obj.name] = entry
    return {
        "objects": objects,
        "meshes": sorted(m.name for m in bpy.data.meshes),
        "materials": sorted(m.name for m in bpy.data.materials),
        "collections": sorted(c.name for c in bpy.data.collections),
        "scene_children": sorted(c.name for c in bpy.context.scene.collection.children),
        "node_groups": sorted(n.name for n in bpy.data.node_groups),
    }


def core_arrays(code: str, **names: str) -> dict[str, np.ndarray]:
    """Run `code` in the core's interpreter (CORE_PYTHON: torch, pyarrow) and return the arrays it binds.

    The LTS venvs hold only bpy, numpy and pytest, so a test that needs the core's own answer (a sample, a read
    sequence) asks the interpreter the add-on itself would use, as the add-on does, instead of importing it here.
    `names` maps each returned key to the expression evaluated after `code`.
    """
    import subprocess

    with tempfile.TemporaryDirectory(prefix="hgca_core_arrays_") as tmp:
        out = Path(tmp) / "out.npz"
        fields = ", ".join(f"{k}=np.asarray({v})" for k, v in names.items())
        script = (f"import sys; sys.path[:0] = [{str(REPO)!r}, {str(REPO / 'tests')!r}]\n"
                  f"import numpy as np\n{code}\nnp.savez({str(out)!r}, {fields})\n")
        done = subprocess.run([CORE_PYTHON, "-c", script], capture_output=True, text=True, timeout=600)
        if done.returncode != 0:
            raise RuntimeError(f"core snippet failed ({CORE_PYTHON}):\n{done.stderr[-4000:]}")
        with np.load(out) as data:
            return {k: data[k] for k in data.files}

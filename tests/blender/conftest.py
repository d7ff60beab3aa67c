"""Fixtures for tests on real bpy: the add-on loaded as an extension from a staged local repository."""
from __future__ import annotations

from bl_helpers import ADDON, CORE_PYTHON, REPO_MODULE, addon_module, prefs  # sets BLENDER_USER_RESOURCES first

import addon_utils  # noqa: E402  (bpy's own module, importable once bpy is)
import bpy  # noqa: E402
import pytest  # noqa: E402

from hgca_blender import build_extension  # noqa: E402


@pytest.fixture(scope="session")
def addon(tmp_path_factory: pytest.TempPathFactory):
    """The staged add-on enabled as `bl_ext.hgca_test.hgca`."""
    repo_dir = tmp_path_factory.mktemp("ext_repo")
    build_extension.stage(repo_dir / "hgca")
    repos = bpy.context.preferences.extensions.repos
    repo = repos.new(name=REPO_MODULE, module=REPO_MODULE, custom_directory=str(repo_dir), source="USER")
    module = addon_utils.enable(ADDON, default_set=True, handle_error=None)
    assert module is not None, f"could not enable {ADDON}"
    yield module
    addon_utils.disable(ADDON, default_set=True)
    repos.remove(repo)


@pytest.fixture(autouse=True)
def empty_file(request: pytest.FixtureRequest):
    """Every test starts from an empty file, the shipped weights and the core interpreter set to CORE_PYTHON."""
    if "addon" in request.fixturenames:
        prefs().python_path = CORE_PYTHON
        prefs().weights_path = ""
    bpy.ops.wm.read_homefile(use_empty=True)
    yield
    if "addon" in request.fixturenames:
        addon_module("jobs.completion").cancel_all()



# bpy 4.2 from PyPI segfaults while the interpreter finalises after this whole suite has passed (exit 139), and
# bpy 4.5 hangs there (still running 30 s after its last result; a few files alone exit 0 at once). The results
# are reported by then, so on these LTS lines, outside xdist workers, the process ends with pytest's own status
# instead of running that teardown. Still open: which registration the crash comes from.
_STATUS: dict[str, int] = {}


def pytest_sessionfinish(session, exitstatus):
    _STATUS["code"] = int(exitstatus)


def pytest_unconfigure(config):
    import os
    import sys

    bpy = sys.modules.get("bpy")
    lts = bpy is not None and tuple(bpy.app.version[:2]) in ((4, 2), (4, 5))
    if not lts or hasattr(config, "workerinput") or "code" not in _STATUS:
        return
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(_STATUS["code"])

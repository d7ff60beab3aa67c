"""*Install Core* and *Check* in the preferences, on real bpy, into the session's fresh Blender user folder.

The install reads hgca's wheel from the staged extension's `core/` folder (as in the zip) and everything else from
a local folder of wheels (`pip download` from this machine's index): the offline path, end to end, then an imported
scan completed with the installed core.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import bpy
import pytest

from hgca_blender.jobs.install_core import EXTRAS  # what Install Core asks pip for

from bl_helpers import CORE_PYTHON, NUSCENES, SMALL_REGION, addon_module, prefs, require_fixture

INSTALL_TIMEOUT_S = 900


@pytest.fixture(scope="session")
def core_wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """hgca's wheel as `make extension` puts it in the zip (HGCA_WHEEL: one built already)."""
    given = os.environ.get("HGCA_WHEEL")
    if given:
        return Path(given)
    from hgca_blender import build_extension

    return build_extension.build_wheel(tmp_path_factory.mktemp("wheel"), python=CORE_PYTHON)


@pytest.fixture(scope="session")
def wheels_folder(tmp_path_factory: pytest.TempPathFactory, core_wheel: Path) -> Path:
    """Every wheel the core needs, fetched once from the index pip is configured with (local on this machine)."""
    folder = tmp_path_factory.mktemp("wheels")
    done = subprocess.run([CORE_PYTHON, "-m", "pip", "download", "-q", "-d", str(folder), f"{core_wheel}[{EXTRAS}]",
                           "torch==2.13.0"], capture_output=True, text=True, timeout=1800)
    if done.returncode != 0:
        pytest.skip(f"pip cannot fetch the core's dependencies here: {done.stderr[-500:]}")
    (folder / core_wheel.name).unlink(missing_ok=True)  # hgca itself comes from the extension
    return folder


@pytest.fixture
def shipped(addon, core_wheel: Path):
    """The staged extension carrying hgca's wheel in core/, as the built zip does."""
    installer = addon_module("jobs.installer")
    folder = installer.WHEEL_DIR
    folder.mkdir(exist_ok=True)
    shutil.copy2(core_wheel, folder / core_wheel.name)
    yield installer
    shutil.rmtree(folder, ignore_errors=True)


def drive(job, timeout: float = INSTALL_TIMEOUT_S) -> list[float]:
    seen = []
    deadline = time.monotonic() + timeout
    while job.poll_once():
        seen.append(job.progress)
        assert time.monotonic() < deadline, job.status
        time.sleep(0.1)
    return seen


def test_core_environment_lives_in_the_extensions_user_folder(addon) -> None:
    env = addon_module("jobs.installer").env_dir()
    assert Path(os.environ["BLENDER_USER_RESOURCES"]) in env.parents
    assert env.parent == Path(bpy.utils.extension_path_user(addon_module("jobs.installer").PACKAGE))


def test_offline_without_wheels_is_refused_before_anything_starts(shipped) -> None:
    core = addon_module("jobs.core")
    with pytest.raises(core.CoreError, match="online access is off"):
        shipped.start_install(sys.executable, wheels="", online=False)
    assert not shipped.env_dir().exists() and shipped.running_install() is None
    with pytest.raises(core.CoreError, match="does not exist"):
        shipped.start_install(sys.executable, wheels="/no/such/folder")


def test_install_without_a_shipped_wheel_says_so(addon) -> None:
    core = addon_module("jobs.core")
    with pytest.raises(core.CoreError, match="carries no hgca wheel"):
        addon_module("jobs.installer").start_install(sys.executable, wheels=str(NUSCENES.parent))


def test_check_fails_on_a_python_without_torch(addon, tmp_path: Path) -> None:
    """A Python that has hgca_core on its path but no torch does not pass the check."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(tmp_path / "bare")], check=True)
    (site,) = (tmp_path / "bare" / "lib").glob("python3*/site-packages")
    (site / "hgca_checkout.pth").write_text(str(Path(__file__).resolve().parents[2]) + "\n")
    bare = tmp_path / "bare" / "bin" / "python"
    assert subprocess.run([str(bare), "-m", "hgca_core.cli", "--version"], capture_output=True).returncode == 0
    prefs().python_path = str(bare)
    prefs().check_result = ""
    with pytest.raises(RuntimeError):
        bpy.ops.hgca.check_python()
    assert prefs().check_result.startswith("Error") and "torch" in prefs().check_result


def test_check_passes_on_the_core_and_loads_the_weights(addon) -> None:
    prefs().python_path = CORE_PYTHON
    assert bpy.ops.hgca.check_python() == {"FINISHED"}
    assert "torch 2.13.0" in prefs().check_result and "weights load" in prefs().check_result


def test_cancel_leaves_no_environment(shipped, wheels_folder: Path) -> None:
    job = shipped.start_install(sys.executable, wheels=str(wheels_folder))
    deadline = time.monotonic() + 120
    while job.poll_once() and not shipped.env_dir().with_name("core_env.new").exists():
        assert time.monotonic() < deadline
        time.sleep(0.05)
    job.cancel()
    assert job.state == "cancelled"
    assert not shipped.env_dir().exists() and not shipped.env_dir().with_name("core_env.new").exists()


@pytest.mark.slow
def test_install_core_offline_then_complete_a_scan_with_it(shipped, wheels_folder: Path) -> None:
    """From the wheels folder into the fresh user folder; the preferences then point at the new core, its check
    passes, and an imported scan completes with it."""
    require_fixture(NUSCENES)
    prefs().python_path = ""
    prefs().wheels_dir = str(wheels_folder)
    t0 = time.monotonic()
    assert bpy.ops.hgca.install_core() == {"FINISHED"}
    job = shipped.running_install()
    progress = drive(job)
    took = time.monotonic() - t0
    assert job.state == "done", f"{job.error}\n{job.log.read_text()[-3000:]}"
    assert progress == sorted(progress) and job.progress == 1.0
    python = Path(prefs().python_path)
    assert python == shipped.env_dir() / "bin" / "python" and python.exists()
    assert "torch" in job.log.read_text()
    found = shipped.check_core(str(python))
    assert found["torch"].startswith("2.13.0") and found["python"].startswith(str(shipped.env_dir()))
    print(f"install took {took:.0f} s")

    assert bpy.ops.import_scene.hgca_lidar(filepath=str(NUSCENES)) == {"FINISHED"}
    scan = bpy.context.selected_objects[0] if bpy.context.selected_objects else bpy.data.objects[0]
    bpy.context.view_layer.objects.active = scan
    scan.select_set(True)
    props = bpy.context.scene.hgca
    props.region_mode = "NUMBERS"
    props.region_center, props.region_size = SMALL_REGION[:3], SMALL_REGION[3:6]
    props.samples, props.stage, props.t1 = 1, "coarse", 2
    assert bpy.ops.hgca.complete() == {"FINISHED"}
    jobs = addon_module("jobs.completion")
    completion = jobs.active_job(bpy.context.scene.name)
    assert completion.cmd[0] == str(python)
    drive(completion, 300)
    assert completion.state == "done", completion.error
    (result,) = bpy.data.collections[completion.collection_name].objects
    assert len(result.data.polygons) > 100


def test_install_progress_moves_while_pip_is_silent_and_speaks_plainly(monkeypatch, capsys, tmp_path) -> None:
    """pip prints nothing while it unpacks torch (about a minute): heartbeat records keep the bar moving every
    HEARTBEAT_S; its retry warnings reach the status line as a plain sentence, the raw line only in the log."""
    import io
    import json as json_

    from hgca_blender.jobs import install_core

    monkeypatch.setattr(install_core, "HEARTBEAT_S", 0.2)
    script = ("import time\nprint('Collecting numpy<2', flush=True)\n"
              "print(\"WARNING: Retrying (Retry(total=4, connect=None)) after connection broken by "
              "'ReadTimeoutError'\", flush=True)\nprint('Installing collected packages: torch', flush=True)\n"
              "time.sleep(1.5)\nprint('Successfully installed torch', flush=True)\n")
    log = io.StringIO()
    install_core.run_logged([sys.executable, "-c", script], log, "pip", [0])
    records = [json_.loads(line) for line in capsys.readouterr().out.splitlines()]
    beats = [r for r in records if r["stage"] == "install" and r["total"] == int(install_core.INSTALL_S)]
    assert len(beats) >= 4, records
    assert [b["step"] for b in beats] == sorted(b["step"] for b in beats) and beats[-1]["step"] >= 1
    messages = [r["message"] for r in records]
    assert not any("Retry(total" in m for m in messages)
    assert any("pip is retrying" in m for m in messages) and "Retry(total=4" in log.getvalue()

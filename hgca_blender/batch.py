"""Headless completion into a .blend, optionally with a preview render.

    blender --background --python hgca_blender/batch.py -- SCAN... --samples 2 --stage coarse \\
        --out scene.blend [--region cx,cy,cz,sx,sy,sz,yaw] [--render preview.png]
    python -m hgca_blender.batch SCAN... --out scene.blend        (bpy module)
    ... SCAN... --poses P --drive DIR --out drive.blend           (a whole drive, `hgca drive`, into DIR)

Timers never fire in background mode, so the job is driven by calling `poll_once()` in a loop; the
code path is otherwise the one the UI uses (import via `hgca read`, `CompletionJob`, mesh building).
"""
from __future__ import annotations

import sys
from pathlib import Path


def _package_of(folder: Path):
    """This folder as a package: the one Blender loaded it as (an enabled extension, `bl_ext.<repo>.hgca`), else
    imported from its own `__init__.py` under the folder's name (a checkout's `hgca_blender`, an unzipped copy)."""
    import importlib
    import importlib.util

    init = folder / "__init__.py"
    for name, module in list(sys.modules.items()):
        if getattr(module, "__file__", None) and Path(module.__file__).resolve() == init:
            return importlib.import_module(f"{name}.batch")
    name = folder.name if folder.name.isidentifier() else "hgca_blender"
    spec = importlib.util.spec_from_file_location(name, init, submodule_search_locations=[str(folder)])
    package = importlib.util.module_from_spec(spec)
    sys.modules[name] = package
    spec.loader.exec_module(package)
    return importlib.import_module(f"{name}.batch")


if __name__ == "__main__" and not __package__:
    # Run as a script (`blender -b --python .../hgca/batch.py -- ...`, from a checkout or the installed
    # extension, whose folder is `hgca`): import the package this file lies in and run from it.
    _package_batch = _package_of(Path(__file__).resolve().parent)
    sys.exit(_package_batch.main(_package_batch.script_args(sys.argv)))

import argparse
import time
from typing import Callable

import bpy

from . import preferences, settings
from .jobs import completion, core, default_region, job_inputs
from .operators import import_scans
from .scene import georef, mesh_build, preview, region


def script_args(argv: list[str]) -> list[str]:
    """Arguments meant for this script: after `--` when present (Blender's convention), else argv[1:]."""
    return argv[argv.index("--") + 1:] if "--" in argv else argv[1:]


def _size(text: str) -> tuple[int, int]:
    """`--render-size 1280x720`."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be WIDTHxHEIGHT, got {text!r}") from None
    if not (16 <= w <= 16384 and 16 <= h <= 16384):
        raise argparse.ArgumentTypeError(f"size must be 16..16384 pixels a side, got {text!r}")
    return w, h


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="hgca_blender.batch", description=__doc__.split("\n")[0])
    p.add_argument("scans", nargs="+", help="scan files (any format `hgca read` accepts)")
    p.add_argument("--poses", default=None, help="poses JSON for the scans")
    p.add_argument("--frames", default="", metavar="START:STOP[:STEP]",
                   help="frames of a sequence folder given as the one scan (default: the 5 around the middle)")
    p.add_argument("--topic", default="", help="the point cloud topic of a ROS bag given as the one scan")
    p.add_argument("--out", required=True, help="output .blend")
    p.add_argument("--region", default=None, help="cx,cy,cz,sx,sy,sz[,yaw_deg] (default: `hgca region`'s box, "
                                                  "38.4 x 38.4 x 8 m around the sensor, 1 m below the ground)")
    # the core's settings, each made from the schema the extension build writes from hgca_core.config: default,
    # bounds, choices and help are the core's (the drive's as --workers, --tile-size, --overlap)
    for name in settings.LIMITS:
        flag = "--" + name.removeprefix("drive_").replace("_", "-")
        kind = {"choices": settings.choices(name)} if "choices" in settings.LIMITS[name] else {
            "type": settings.parse_type(name)}
        what = "--drive: " if name.startswith("drive_") else ""
        p.add_argument(flag, dest=name, default=settings.default(name),
                       help=f"{what}{settings.HELP.get(name, '')} (default {settings.default(name)})", **kind)
    p.add_argument("--simplify", choices=("bake", "modifier"), default="bake",
                   help="bake: the core simplifies to --max-faces; modifier: keep every triangle under a Decimate "
                        "modifier showing --max-faces (tunable in Blender, larger .blend)")
    p.add_argument("--color", choices=("observed", "agreement"), default="observed",
                   help="colour the meshes by observed/generated or by agreement across --samples (2 or more)")
    p.add_argument("--weights", default=None, help="coarse weights passed to `hgca complete --weights`")
    p.add_argument("--python", default=None, help="interpreter with hgca_core (default: auto-detect)")
    p.add_argument("--render", default=None, help="also render a preview PNG with Cycles (CPU)")
    p.add_argument("--render-samples", type=int, default=16)
    p.add_argument("--render-size", type=_size, default=(640, 480), metavar="WxH", help="preview size in pixels")
    p.add_argument("--timeout", type=float, default=3600.0, help="give up on the completion after this many seconds")
    p.add_argument("--drive", default=None, metavar="DIR",
                   help="complete the whole drive tile by tile (`hgca drive`, scans in trajectory order) into DIR "
                        "(kept: running again resumes); one object per tile per sample")
    return p


def _log(message: str) -> None:
    print(f"hgca batch: {message}", flush=True)


def core_python(args: argparse.Namespace) -> str:
    """--python, else the add-on's preference (what *Install Core* set), else the core it installed, else one
    found on this machine ("" when none)."""
    return args.python or preferences.core_python()


def run(args: argparse.Namespace) -> int:
    python = core_python(args)
    if not python:
        _log(f"error: no interpreter with hgca_core found: run Install Core in the add-on's preferences, pass "
             f"--python or set {preferences.ENV_VAR}")
        return 2
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    t0 = time.perf_counter()
    try:
        obj, skipped, dropped = import_scans.import_scans(python, [Path(s) for s in args.scans],
                                                              scene.collection,
                                                              Path(args.poses) if args.poses else None, scene=scene,
                                                              frames=args.frames, topic=args.topic)
    except (core.CoreError, ValueError, OSError) as exc:
        _log(f"error: {exc}")
        return 2
    _log(f"imported {len(obj.data.vertices):,} points as '{obj.name}' in {time.perf_counter() - t0:.1f} s"
         + (f" (skipped attributes: {', '.join(skipped)})" if skipped else "")
         + (f"; {import_scans.dropped_text(dropped)}" if dropped else ""))
    if args.drive:
        return _drive(args, python, scene, t0)
    try:
        # a --region goes to the core as typed (world), as `hgca complete --region` takes it
        world_box = (region.parse_region(args.region) if args.region
                     else default_region.default_world_region(python, scene, [obj]))
    except (region.RegionError, core.CoreError) as exc:
        _log(f"error: {exc}")
        return 2
    box = georef.region_to_scene(scene, world_box)   # Blender coordinates: the preview camera frames it
    region.create_region_box(scene.collection, box, world=world_box)
    params = completion.CompletionParams(python=python, **job_inputs.source_inputs(scene, [obj]),
                                   region=world_box, samples=args.samples, seed=args.seed,
                                   stage=args.stage, quality=args.quality, device=args.device, t1=args.t1, t2=args.t2,
                                   max_faces=0 if args.simplify == "modifier" else args.max_faces,
                                   decimate_to=args.max_faces if args.simplify == "modifier" else 0,
                                   scene_name=scene.name,
                                   extra_args=["--weights", args.weights] if args.weights else [])
    job = _run_job(lambda: completion.start_job(params), args.timeout, "completion", t0)
    if job is None:
        return 2
    results = sorted(bpy.data.collections[job.collection_name].objects, key=lambda o: int(o["hgca_sample"]))
    if args.color == "agreement" and not mesh_build.color_results_by(results, mesh_build.AGREEMENT_COLOR):
        _log("error: --color agreement needs --samples 2 or more")
        return 2
    for obj in results:
        mod = obj.modifiers.get(mesh_build.DECIMATE_MODIFIER)
        _log(f"sample {int(obj['hgca_sample'])}: {len(obj.data.polygons):,} triangles"
             + (f", {mod.face_count:,} shown by the Decimate modifier" if mod is not None else ""))
    if args.render:
        preview.add_camera_and_sun(scene, box)
        preview.configure_cycles(scene, samples=args.render_samples, resolution=args.render_size)
    out = _save(args.out)
    size = out.stat().st_size
    _log(f"saved {out}: {size / 2**20:.1f} MiB, {size / 2**20 / max(len(results), 1):.1f} MiB a sample")
    if args.render:
        png = preview.render_png(scene, Path(args.render))
        _log(f"rendered {png}")
    return 0


def _run_job(start: Callable[[], core.Job], timeout: float | None, what: str, t0: float,
             hint: str = "") -> core.Job | None:
    """Start a job and drive it to its end, logging its status; None (the reason logged) unless it ended done."""
    try:
        job = start()
    except core.CoreError as exc:
        _log(f"error: {exc}")
        return None
    state = _wait_logged(job, timeout)
    completion.poll_all()
    if state != "done":
        _log(f"error: {what} {state}: {job.error or job.status}{hint}")
        return None
    _log(f"{job.status} after {time.perf_counter() - t0:.1f} s")
    return job


def _save(path: str) -> Path:
    """Save the open file as `path` (its folder made when missing); returns the resolved path."""
    out = Path(path).resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(out), check_existing=False)
    return out


def _wait_logged(job: core.Job, timeout: float | None) -> str:
    """Drive the job to its end, logging each new status line; returns the final state."""
    last = [""]

    def show(j: core.Job) -> None:
        if j.status != last[0]:
            last[0] = j.status
            _log(f"{j.progress * 100:5.1f}% {j.status}")

    return job.wait(timeout=timeout, on_poll=show)


def _drive(args: argparse.Namespace, python: str, scene: bpy.types.Scene, t0: float) -> int:
    """`--drive DIR`: `hgca drive` on the scans, its tiles into one collection, then save."""
    from .jobs import drive_job

    params = drive_job.DriveParams(
        python=python, scans=list(args.scans), out_dir=args.drive, poses=args.poses, samples=args.samples,
        seed=args.seed, stage=args.stage, quality=args.quality, device=args.device, t1=args.t1, t2=args.t2,
        max_faces=args.max_faces,
        workers=args.drive_workers, tile_size=args.drive_tile_size, overlap=args.drive_overlap, scene_name=scene.name,
        extra_args=["--weights", args.weights] if args.weights else [])
    if _run_job(lambda: drive_job.start_drive_job(params), args.timeout, "drive", t0,
                f" (finished tiles stay in {args.drive})") is None:
        return 2
    _log(f"saved {_save(args.out)}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(script_args(sys.argv) if argv is None else argv)
    return run(args)


if __name__ == "__main__":
    sys.exit(main())

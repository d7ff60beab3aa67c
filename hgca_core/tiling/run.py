"""`hgca_core.drive(...)`, the Python API of `hgca drive`: a whole drive completed tile by tile.

Read the scans (float64 world points after their poses), plan tiles along the sensor positions (`plan`), place
each tile on its own ground, name each tile's result by a content key (`tile.TileJob.key`: its scans' content,
region, seed, settings, weights, and the keys of the neighbours it is conditioned on), skip the tiles whose
key is already in DIR/cache (a resumed run), run the rest (`runners`: in-process or Ray), then cut and weld
one mesh per sample (`merge`). drive.json is rewritten (atomically) after every finished tile, so a crash or
Ctrl-C loses at most the tiles in flight.
"""
from __future__ import annotations

import os
import signal
import socket
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from hgca_core.config import TILE_OVERLAP, TILE_SIZE, DriveConfig, check_seed_span
from hgca_core.errors import InputError
from hgca_core.geometry.region import DEFAULT_SIZE, Region
from hgca_core.io.digest import file_digest
from hgca_core.tiling.merge import merge_sample, write_piece
from hgca_core.tiling.inputs import DriveScan, read_drive_inputs
from hgca_core.tiling.plan import TilePlan, neighbours, plan_tiles, tile_region
from hgca_core.tiling.records import check_cache, check_meshes, checksums, made_from, recorded, sweep
from hgca_core.tiling.store import DriveStore
from hgca_core.tiling.tile import Settings, TileJob, cells_of

Report = Callable[[str, int, int, str, int], None]   # (stage, step, total, message, sample): pipeline.ProgressFn


def plan_drive(scans: list[DriveScan], size: float = TILE_SIZE, overlap: float = TILE_OVERLAP,
               scans_per_tile: int = DriveConfig.scans_per_tile) -> tuple[list[TilePlan], list[Region], dict]:
    """The tiles of a drive (`plan.plan_tiles` on the scans' sensor positions), each placed on its own ground,
    and the plan as JSON (`plan_document`): what `hgca drive --plan-only --json` prints and a run reports."""
    positions = np.array([s.position for s in scans])
    plans = plan_tiles(positions, size, overlap, scans_per_tile)
    tile_size = (float(size), float(size), DEFAULT_SIZE[2])
    regions = [tile_region(t, np.concatenate([scans[i].points for i in t.scans]), tile_size) for t in plans]
    doc = {"size": list(tile_size), "overlap": overlap, "stride": size - overlap, "scans_per_tile": scans_per_tile,
           "length": _path_length(positions), "trajectory": positions.tolist(),
           "scans": [{"name": s.name, "position": s.position.tolist(), "points": int(len(s.points)),
                      "origins": int(len(s.origins))} for s in scans],
           "tiles": [{"index": t.index, "phase": t.phase, "arc": round(t.arc, 3), "region": list(r.as_tuple()),
                      "scans": list(t.scans)} for t, r in zip(plans, regions)]}
    return plans, regions, doc


def drive(scans: Sequence[str | os.PathLike], out: str | os.PathLike, poses: str | os.PathLike | None = None,
          fmt: str | None = None, frames: str | None = None, config: DriveConfig | None = None, *,
          topic: str | None = None,
          report: Report | None = None, on_tile: Callable[[int, int, int, str], None] | None = None,
          on_plan: Callable[[dict], None] | None = None,
          on_step: Callable[[int, str, int, int], None] | None = None, **settings) -> dict:
    """Complete the drive seen by `scans` (scan files in any order,
    `order` finds the drive's; or one sequence folder, bag or E57 with `frames`, a bag's cloud `topic`)
    into DIR=`out` as `config` says (`DriveConfig`, default: its defaults); `settings` change single fields,
    the drive's (size=, workers=, ...) or each tile's completion's (stage=, seed=, t1=, ...). Returns
    drive.json's content.

    Tiles are `size` m squares (8 m high) along the sensor positions, `overlap` m apart; each is completed from
    its `scans_per_tile` nearest scans with their rays (`free_space` as `hgca complete --free-space`), sample k
    of tile i with seed + i * samples + k. With `seams`, odd tiles run second with their finished neighbours'
    coarse cells in their initial state. `workers` > 1 or an `address` runs tiles on Ray, each declaring
    `tile_memory` bytes (default: `pipeline.memory_need` of a tile) so no node takes more tiles at once than
    fit. `report(stage, step, total, message, sample)` hears of reading and merging; `on_plan(plan)` gets
    `plan_document` once the tiles are placed; `on_step(index, stage, step, total)` hears of the chain steps of
    a tile running in this process (Ray's tiles run elsewhere and report when done); `on_tile(done, total, index, state)` hears of each tile: state
    "cached" (finished by an earlier run) or "queued" for every tile first, then "running" (in-process runs
    only) and "done"; `done` counts finished tiles, resumed ones too. Only one run writes DIR at a time
    (`DriveStore.lock`); a signal that ends the `hgca` CLI leaves drive.json "interrupted".
    """
    from hgca_core.interrupt import last_words
    from hgca_core.pipeline import check_device, check_memory, load_models, memory_need

    cfg = (config or DriveConfig()).with_(**settings)
    c = cfg.completion
    samples, seed = c.samples, c.seed
    workers, address = cfg.workers, cfg.address

    t_start = time.perf_counter()
    say = report or (lambda *a: None)
    tell = on_tile or (lambda *a: None)
    check_device(c.device)
    if workers > 1 or address:
        from hgca_core.tiling.runners import require_ray

        require_ray()
    paths = [os.fspath(p) for p in scans]
    if not paths:
        raise InputError("no scan files given")
    store = DriveStore(out)
    store.check()
    ext = "." + cfg.mesh_format
    threads = cfg.threads or max(1, (os.cpu_count() or 1) // workers)
    tile = Settings(c, threads)
    _check_outputs(paths, poses, store, tile.files())
    load_models(c.stage, c.coarse_file(), c.fine_file(), c.device)   # bad weights fail before reading a scan
    digests = tuple(file_digest(p) for p in tile.files())

    inputs = read_drive_inputs(paths, poses, fmt, frames, say, topic)
    t_read = time.perf_counter()
    plans, regions, plan_doc = plan_drive(inputs, cfg.size, cfg.overlap, cfg.scans_per_tile)
    memory = cfg.tile_memory or memory_need(regions[0])
    if workers == 1 and not address:
        check_memory(regions[0])                                  # on Ray, each node is checked instead
    check_seed_span(seed, len(plans) * samples, "tiles x samples")   # every tile's seeds
    scan_digests = [s.digest() for s in inputs]
    jobs = _jobs(plans, regions, scan_digests, seed, samples, tile, digests, cfg.seams)

    store.prepare()
    previous = store.read_manifest()  # None (with a warning) when edited or corrupt: each tile is checked alone
    cached = check_cache(store, jobs, previous)    # what fails its checks (cut short, another drive's) is recomputed
    doc: dict = {}
    try:
        with last_words(lambda signum: _stopped(store, doc, signum)):
            run_no = _start_manifest(store, doc, previous, cached, inputs, plans, jobs, plan_doc, tile, digests,
                                     samples, ext,
                                     {"engine": "ray" if (workers > 1 or address) else "local", "workers": workers,
                                      "threads": threads, "address": address, "tile_memory": memory,
                                      "seams": cfg.seams, "mesh_format": cfg.mesh_format,
                                      "read_s": round(t_read - t_start, 3)})
            store.write_manifest(doc)
            if on_plan:
                on_plan(plan_doc)

            finished = sum(t["status"] == "done" for t in doc["tiles"])
            # a resumed run writes again the tile meshes missing or not matching their checksums, and removes the
            # meshes of other plans (another --size) so that none is left under the names this run writes
            check_meshes(store, doc["tiles"], previous,
                         lambda i: _export_tile(store, store.load(jobs[i].key), regions, ext))
            sweep(store, doc, previous)
            store.write_manifest(doc)
            for t in doc["tiles"]:
                tell(finished, len(jobs), t["index"], "cached" if t["status"] == "done" else "queued")
            pending = _pending(jobs, doc["tiles"], store)
            t_tiles = time.perf_counter()

            def on_result(result: dict) -> None:
                nonlocal finished
                job = jobs[result["index"]]
                store.save(result, made_from(job))
                faces = _export_tile(store, result, regions, ext)
                finished += 1
                t = doc["tiles"][result["index"]]
                t.update({"made_from": made_from(job), "sha256": checksums(store, job.key, t["outputs"])})
                t.update({
                    "status": "done", "seconds": result["seconds"], "run": run_no, "started": result["started"],
                    "finished": result["finished"], "worker": result["worker"], "peak_rss": result["peak_rss"],
                    "faces": faces, "fixed_cells": [s["fixed_cells"] for s in result["samples"]],
                    "free_cells": [s.get("free_cells") for s in result["samples"]]})
                store.write_manifest(doc)
                tell(finished, len(jobs), result["index"], "done")

            runner = None
            try:
                if pending:
                    runner = _runner(workers, threads, address, memory)
                    doc["timings"]["engine_start_s"] = round(time.perf_counter() - t_tiles, 3)
                    runner.run(pending, inputs, on_result, lambda i: tell(finished, len(jobs), i, "running"),
                               on_step=on_step)
            except BaseException as exc:
                doc["status"] = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
                doc["error"] = f"{type(exc).__name__}: {exc}"
                store.write_manifest(doc)
                raise
            finally:
                if runner is not None and hasattr(runner, "close"):
                    runner.close()
            t_merge = time.perf_counter()
            doc["outputs"] = _merge(store, jobs, regions, samples, ext, say)
            t_end = time.perf_counter()
            computed = [t for t in doc["tiles"] if t.get("run") == run_no]
            doc["timings"].update({
                "tiles_s": round(t_merge - t_tiles, 3), "merge_s": round(t_end - t_merge, 3),
                "total_s": round(t_end - t_start, 3), "tiles_computed": len(computed),
                "tiles_per_min": round(60 * len(computed) / max(t_merge - t_tiles, 1e-9), 3)})
            doc["status"] = "complete"
            store.write_manifest(doc)
            return {"format": 1, **doc}
    finally:
        store.unlock()


def _start_manifest(store: DriveStore, doc: dict, previous: dict | None, cached: dict[str, str],
                    inputs: list[DriveScan], plans: list[TilePlan], jobs: list[TileJob], plan_doc: dict,
                    settings: Settings, digests: tuple[str, ...], samples: int, ext: str, run: dict) -> int:
    """Fill `doc` (drive.json) for a new run: the plan, scans and tiles, finished ones (`cached`: the checked
    cache entries' sha256 by key) marked done with what the run that made them recorded (`previous`, the checked
    drive.json or None); returns this run's number."""
    previous = previous or {}
    run_no = int(previous.get("runs", 0)) + 1
    old_tiles = recorded(previous)
    kept = ("seconds", "worker", "run", "peak_rss", "faces", "started", "finished", "fixed_cells", "free_cells")
    files = settings.files()
    doc.update({"status": "running", "runs": run_no, "pid": os.getpid(), "host": socket.gethostname(),
                **{k: run[k] for k in ("engine", "workers", "threads", "address", "tile_memory")},
                "settings": {**settings.keyed(), "weights": [str(p) for p in files], "weights_sha256": list(digests),
                             "device": settings.config.device},
                "plan": {**{k: plan_doc[k] for k in ("size", "overlap", "stride", "scans_per_tile", "length")},
                         "seams": run["seams"], "mesh_format": run["mesh_format"]},
                "scans": [{"file": s.name, "position": s.position.tolist(), "points": int(len(s.points)),
                           "origins": int(len(s.origins)), "sha256": s.digest()} for s in inputs],
                "tiles": [], "outputs": [], "timings": {"read_s": run["read_s"]}})
    for t, job in zip(plans, jobs):
        done = job.key in cached
        entry = {"index": t.index, "phase": t.phase, "arc": round(t.arc, 3), "region": list(job.region),
                 "scans": list(t.scans), "seeds": [job.seed + k for k in range(samples)], "key": job.key,
                 "conditioned_on": list(neighbours(t.index, len(plans))) if job.conditioned_on else [],
                 "status": "done" if done else "pending",
                 "outputs": [str(store.tile_mesh(t.index, k, ext).relative_to(store.root)) for k in range(samples)]}
        if done:
            entry.update({k: v for k, v in old_tiles.get(job.key, {}).items() if k in kept})
            entry.setdefault("run", None)
            entry.update({"made_from": made_from(job), "sha256": {store.relative(store.entry(job.key)):
                                                                   cached[job.key]}})
        doc["tiles"].append(entry)
    return run_no


def _stopped(store: DriveStore, doc: dict, signum: int) -> None:
    """The CLI's last words on a signal: drive.json says the run was interrupted (tiles in flight stay pending)."""
    if doc.get("status") == "running":
        doc["status"] = "interrupted"
        doc["error"] = f"stopped by {signal.Signals(signum).name}"
        store.write_manifest(doc)


def _jobs(plans, regions, scan_digests, seed, samples, settings, digests, seams) -> list[TileJob]:
    """One TileJob per tile, by index; a phase-two job's key includes its neighbours' (phase one) keys."""
    def job(t, cond: tuple[str, ...]) -> TileJob:
        return TileJob(t.index, regions[t.index].as_tuple(), t.scans, tuple(scan_digests[i] for i in t.scans),
                       seed + t.index * samples, settings, digests, cond)

    first = {t.index: job(t, ()) for t in plans if t.phase == 1}
    return [first[t.index] if t.phase == 1 else
            job(t, tuple(first[j].key for j in neighbours(t.index, len(plans))) if seams else ()) for t in plans]


def _pending(jobs: list[TileJob], tiles: list[dict], store: DriveStore) -> list:
    """The tiles still to run, phase one first, with the cells of finished neighbours they are conditioned on."""
    from hgca_core.tiling.runners import Pending

    todo = [j for j, t in zip(jobs, tiles) if t["status"] != "done"]
    todo.sort(key=lambda j: (j.index % 2, j.index))
    out = []
    for job in todo:
        cond = neighbours(job.index, len(jobs)) if job.conditioned_on else ()
        ready = {j: (jobs[j].region, cells_of(store.load(jobs[j].key))) for j in cond if tiles[j]["status"] == "done"}
        out.append(Pending(job, cond, ready))
    return out


def _runner(workers: int, threads: int, address: str | None, memory: float):
    from hgca_core.tiling.runners import LocalRunner, RayRunner

    if workers == 1 and not address:
        return LocalRunner()
    return RayRunner(workers, threads, memory, address)


def _export_tile(store: DriveStore, result: dict, regions: list[Region], ext: str) -> list[int]:
    """Write a finished tile's meshes, each cut to the part the tile owns (so the tiles of a drive partition it),
    to DIR/tiles/<i>_s<k>.ext; returns the uncut face counts."""
    from hgca_core.tiling.merge import cut, tile_piece

    i = result["index"]
    for k, s in enumerate(result["samples"]):
        write_piece(store.tile_mesh(i, k, ext), cut(tile_piece(s, regions[i]), i, regions))
    return [int(len(s["faces"])) for s in result["samples"]]


def _merge(store: DriveStore, jobs: list[TileJob], regions: list[Region], samples: int, ext: str,
           say: Report) -> list[str]:
    outputs = []
    for k in range(samples):
        say("merge", k, samples, f"sample {k + 1}/{samples}", k)
        tile_samples = (store.load(j.key, only=k)["samples"][k] for j in jobs)     # loaded one at a time
        path = store.drive_mesh(k, ext)
        write_piece(path, merge_sample(tile_samples, regions))
        outputs.append(str(path))
    say("merge", samples, samples, "", samples - 1)
    return outputs


def _path_length(positions: np.ndarray) -> float:
    """Length in metres of the path through the sensor positions (x/y)."""
    return float(np.linalg.norm(np.diff(positions[:, :2], axis=0), axis=1).sum()) if len(positions) > 1 else 0.0


def _check_outputs(paths: list[str], poses, store: DriveStore, weights: list[Path]) -> None:
    """No input may be one of the files a drive writes (a drive folder inside the scans' folder is fine); an
    existing drive folder's outputs pass the commands' one output check (`io.paths.check_outputs`)."""
    from hgca_core.io.paths import check_outputs

    root = os.path.realpath(store.root)
    for p in paths:
        if os.path.isdir(p) and os.path.realpath(p) == root:
            raise InputError("the drive folder is the input sequence folder; choose another --out (a folder inside "
                             "it is fine)", str(store.root))
    if store.root.is_dir():
        check_outputs([store.manifest, store.drive_mesh(0, ".ply")], [*paths, poses, *weights], skip=[store.root])
    else:
        store.check_creatable()
    inputs = {os.path.realpath(p) for p in paths} | ({os.path.realpath(os.fspath(poses))} if poses else set())
    for p in inputs:
        if Path(p).parent == Path(os.path.realpath(store.root)) and (Path(p).name == "drive.json"
                                                                     or Path(p).name.startswith("drive_s")):
            raise InputError("an input lies where the drive writes its outputs; choose another --out", p)
        if os.path.realpath(store.tiles) == str(Path(p).parent) or os.path.realpath(store.cache) == str(Path(p).parent):
            raise InputError("an input lies in the drive's tiles/ or cache/ folder; choose another --out", p)

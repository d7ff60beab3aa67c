"""Scan files in, mesh files out: what `hgca complete` does, as one library call.

`complete_files(scans, out, config)` reads the scans (any format or sequence folder `hgca read` takes, with a
poses file), gives every point its sensor origin, completes the region and writes one mesh per sample to
OUT_s<i>.<format>, all samples or none. The CLI is argv -> `CompletionConfig` -> this call, so a Python user gets
the CLI's mesh, bit for bit, without assembling the steps by hand.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Sequence

from hgca_core.config import MESH_FORMATS, CompletionConfig
from hgca_core.errors import InputError

MESH_EXTS = tuple("." + f for f in MESH_FORMATS)
DEFAULTS = CompletionConfig()


def mesh_format(out: str | os.PathLike, asked: str | None) -> str:
    """The mesh format of output `out` (with `asked`, a --mesh-format): the one asked for, else the extension's; an
    extension that is a mesh format and disagrees with the one asked for is refused."""
    out = str(out)
    ext = Path(out).suffix.lower()
    if asked is None:
        if ext not in MESH_EXTS:
            raise InputError(f"output must end in one of {', '.join(MESH_EXTS)} (or give --mesh-format)", out)
        return ext[1:]
    if ext in MESH_EXTS and ext[1:] != asked:
        raise InputError(f"the output's extension {ext} disagrees with --mesh-format {asked}", out)
    return asked


def output_paths(out: str | os.PathLike, samples: int, fmt: str | None = None) -> list[Path]:
    """OUT_s<i>.<format> for each sample (the names every sample's mesh is written to)."""
    if str(out).endswith(("/", os.sep)):
        raise InputError("the output ends in a path separator, so it names a folder: give the mesh file's name "
                         "(e.g. DIR/completion.ply)", str(out))
    path = Path(out)
    fmt = mesh_format(out, fmt)
    stem = path.stem if path.suffix.lower() in MESH_EXTS else path.name
    return [path.with_name(f"{stem}_s{i}.{fmt}") for i in range(samples)]


def complete_files(scans: Sequence[str | os.PathLike], out: str | os.PathLike,
                   config: CompletionConfig | None = None, *, poses: str | os.PathLike | None = None,
                   region: str | None = None, frames: str | None = None, topic: str | None = None,
                   fmt: str | None = None, mesh_format: str | None = None, progress: Callable | None = None, **settings) -> list[Path]:
    """Complete scan files into mesh files; returns the paths written (OUT_s<i>.<format>, one per sample).

    `config` (default: its defaults) with `settings` (any of its fields: samples=, seed=, stage=, quality=, ...)
    says how; `region` is the CLI's "cx,cy,cz,sx,sy,sz[,yaw_deg]" (None: the default box around the first
    sensor); `frames` picks a sequence folder's (bag's, E57's) sweeps, `topic` a bag's cloud topic. Every check that can fail on the arguments runs before
    the scans are read; no output may overwrite an input; the meshes are moved into place together (an error or
    a signal leaves none)."""
    from hgca_core.geometry.region import Region
    from hgca_core.io.memory import check_read_memory
    from hgca_core.io.paths import check_outputs
    from hgca_core.pipeline import check_device, check_memory

    cfg = (config or DEFAULTS).with_(**settings)
    if cfg.semantics_weights is not None and not cfg.semantics:
        cfg = cfg.with_(semantics=True)
    scans = [str(s) for s in scans]
    poses = None if poses is None else str(poses)
    paths = output_paths(out, cfg.samples, mesh_format)
    check_outputs(paths, [*scans, poses, cfg.coarse_file(), cfg.fine_file(), cfg.semantics_weights])
    check_device(cfg.device)
    check_read_memory(scans)
    box = Region.parse(region) if region else None
    if box is not None:
        check_memory(box)
    report = progress or (lambda *a: None)

    from hgca_core.io import write_mesh, write_mesh_npz
    from hgca_core.io.atomic import AtomicBatch
    from hgca_core.io.sequence import read_inputs
    from hgca_core.pipeline import complete, load_models

    if cfg.semantics:
        from hgca_core.models.weights import load_semantics

        load_semantics(cfg.semantics_weights, cfg.device)
    # bad weights fail before any reading; complete() gets the same models again from the loaders' cache
    load_models(cfg.stage, cfg.coarse_file(), cfg.fine_file(), cfg.device)
    report("read", 0, 1, f"{len(scans)} scan(s)", 0)
    scan = read_inputs(scans, poses=poses, fmt=fmt, frames=frames, topic=topic)
    report("read", 1, 1, f"{len(scan.points)} points", 0)
    index = None
    if scan.origins is not None and len(scan.origins) and cfg.free_space != "off":
        from hgca_core.geometry.freespace import ray_origins

        index = ray_origins(scan.origins, scan.attributes, scan.points)
    results = complete(scan.points, region=box, origins=scan.origins, config=cfg, progress=progress,
                       origin_index=index)
    with AtomicBatch() as batch:  # every sample or none: an interrupted write leaves nothing behind
        for i, (res, path) in enumerate(zip(results, paths)):
            report("write", i, len(paths), path.name, i)
            if path.suffix.lower() == ".npz":
                write_mesh_npz(path, res.mesh.vertices, res.mesh.faces, res.observed_distance, batch=batch,
                               normals=res.mesh.vertex_normals,
                               face_material=res.mesh.face_attributes.get("material"),
                               face_label=res.mesh.face_attributes.get("label"),
                               face_label_agreement=res.mesh.face_attributes.get("label_agreement"))
            else:
                write_mesh(path, res.mesh, batch=batch)
        batch.commit()
    report("write", len(paths), len(paths), "", len(paths) - 1)
    return paths

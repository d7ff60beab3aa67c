"""Meshes from the fine stage's output (the coarse stage's blocky mesh is `hgca_core.geometry.voxel_mesh`).

Unsigned distance decoded on a 5 cm grid (`udf_grid`) -> one open surface at its zero level
(`hgca_core.geometry.udf_surface`) -> cleanup (`hgca_core.geometry.mesh_clean`): floating fragments, consistent
orientation towards the sensors, pinholes. `finish_mesh` adds per-vertex normals and the observed / generated face
split every output carries; `decimate` makes a mesh light.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import numpy as np
import torch
import trimesh

from hgca_core.geometry.keys import pack, unpack

if TYPE_CHECKING:
    from hgca_core.geometry.nearest import PointIndex

# ---------------------------------------------------------------------------------------------------------------
# Unsigned distance -> mesh (the fine stage, paper App. "Other Implementation Details")
#
# Frames: the decoder works in the *cell frame*, where 10 cm cell c has its centre at c * voxel (the region frame,
# since 10 cm cells are made by rounding). The 5 cm evaluation grid has point g at g * res, so with voxel = 2 res a
# cell owns the grid points 2c - 1, 2c, 2c + 1 per axis (its centre, faces, edges and corners). Grid points outside
# every occupied cell are never evaluated: they take the clamp value (one cell), which is what the decoder returns
# there anyway (no occupied cell among their 8 nearest cell centres).
# ---------------------------------------------------------------------------------------------------------------
UdfFn = Callable[[torch.Tensor], torch.Tensor]


# Defaults of the fine stage's cleanup (see `udf_mesh`)
MIN_AREA = 0.05          # m^2: connected pieces smaller than a 22 x 22 cm square are specks, not objects
PINHOLE_EDGES = 12       # boundary loops of at most this many edges (~0.5 m around at 5 cm) are closed
# Defaults of `finish_mesh`
DEFAULT_MAX_FACES = 1_000_000
OBSERVED_SPLIT = 0.15    # m: faces whose vertices are on average farther from the input are "generated"


def _as_field(decoder: object, cells: torch.Tensor, latents: torch.Tensor | None) -> UdfFn:
    """The query function: `decoder.field(cells, latents)` for an autoencoder, or `decoder` itself when it is
    already a function of region-frame points (metres) -> unsigned distance (metres), e.g. an analytic one."""
    if hasattr(decoder, "field"):
        return decoder.field(cells, latents)  # type: ignore[attr-defined]
    if callable(decoder):
        return decoder  # type: ignore[return-value]
    raise TypeError(f"decoder must have .field(cells, latents) or be callable, got {type(decoder).__name__}")


def _cells_tensor(cells: np.ndarray | torch.Tensor) -> torch.Tensor:
    t = cells.cpu() if isinstance(cells, torch.Tensor) else torch.from_numpy(np.asarray(cells))
    return t.long().reshape(-1, 3)


def _ratio(voxel: float, res: float) -> int:
    r = voxel / res
    if res <= 0 or abs(r - round(r)) > 1e-6 or round(r) < 1:
        raise ValueError(f"voxel ({voxel}) must be a whole multiple of res ({res})")
    return int(round(r))


def udf_grid_points(cells: np.ndarray | torch.Tensor, voxel: float = 0.1, res: float = 0.05) -> np.ndarray:
    """Integer indices (G, 3) of the res-grid points inside or on the boundary of occupied cells, unique, sorted.

    Point g lies at g * res in the cell frame; cell c (centre c * voxel, r = voxel / res) owns the points with
    |g - r c| <= r / 2 on every axis.
    """
    c = (cells.cpu().numpy() if isinstance(cells, torch.Tensor) else np.asarray(cells)).astype(np.int64).reshape(-1, 3)
    if len(c) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    r = _ratio(voxel, res)
    h = r // 2
    o = np.arange(-h, h + 1)
    offs = np.stack(np.meshgrid(o, o, o, indexing="ij"), -1).reshape(-1, 3)
    g = (c[:, None, :] * r + offs[None]).reshape(-1, 3)
    return unpack(np.unique(pack(g)), batched=False)


def udf_grid(decoder: object, cells: np.ndarray | torch.Tensor, latents: torch.Tensor | None = None,
             voxel: float = 0.1, res: float = 0.05, chunk: int = 1 << 15) -> tuple[np.ndarray, np.ndarray]:
    """(grid indices (G, 3) int64, unsigned distances (G,) float32 metres) on the res-grid around occupied cells.

    A decoder with `grid_udf(cells, latents, res, chunk)` (the autoencoder: the same values, evaluated per cell
    without neighbour search) is asked directly; otherwise its query function sees at most `chunk` points at a
    time. Either way memory stays bounded whatever the scene size.
    """
    cells_t = _cells_tensor(cells)
    _ratio(voxel, res)
    if len(cells_t) == 0:
        return np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.float32)
    if hasattr(decoder, "grid_udf") and latents is not None:
        with torch.no_grad():
            g_t, vals_t = decoder.grid_udf(cells_t, latents, res, chunk)  # type: ignore[attr-defined]
        return g_t.cpu().numpy(), vals_t.float().cpu().numpy()
    g = udf_grid_points(cells_t, voxel, res)
    field = _as_field(decoder, cells_t, latents)
    vals = np.empty(len(g), dtype=np.float32)
    with torch.no_grad():
        for a in range(0, len(g), chunk):
            q = torch.from_numpy(g[a:a + chunk].astype(np.float32) * np.float32(res))
            vals[a:a + chunk] = field(q).float().cpu().numpy()
    return g, vals


def project_to_zero(field: UdfFn, points: np.ndarray, steps: int = 1, max_dist: float | None = None,
                    chunk: int = 1 << 16) -> np.ndarray:
    """Move points onto the zero level along the distance gradient: p <- p - d(p) grad d / |grad d|.

    One step is exact for a true distance function; points whose distance is at the clamp (no gradient) or
    above `max_dist` stay where they are.
    """
    p = np.asarray(points, dtype=np.float64).copy()
    for _ in range(max(0, steps)):
        for a in range(0, len(p), chunk):
            q = torch.from_numpy(p[a:a + chunk].astype(np.float32)).requires_grad_(True)
            with torch.enable_grad():
                d = field(q)
                (grad,) = torch.autograd.grad(d.sum(), q)
            n = grad.norm(dim=1, keepdim=True)
            ok = (n[:, 0] > 1e-6) & (d.detach() > 0)
            if max_dist is not None:
                ok &= d.detach() < max_dist
            step = (d.detach()[:, None] * grad / n.clamp(min=1e-6)) * ok[:, None]
            p[a:a + chunk] -= step.double().numpy()
    return p


def udf_mesh(decoder: object, cells: np.ndarray | torch.Tensor, latents: torch.Tensor | None = None,
             lower_corner: float | np.ndarray | None = None, voxel: float = 0.1, res: float = 0.05,
             chunk: int = 1 << 15, min_area: float = MIN_AREA, pinhole_edges: int = PINHOLE_EDGES,
             points: np.ndarray | None = None, sensors: np.ndarray | None = None, fair: bool = True,
             timings: dict | None = None, tree: PointIndex | None = None, workers: int | None = None
             ) -> trimesh.Trimesh:
    """One open surface at the zero level of the unsigned distance around occupied 10 cm cells (5 cm grid).

    decoder: an autoencoder (anything with `.field(cells, latents)`) or a function of (Q, 3) cell-frame points
      (metres) -> (Q,) unsigned distances (metres), clamped at `voxel`.
    cells: (N, 3) int occupied cells; latents: (N, K) their codes (ignored by a plain function).
    lower_corner: where cell c's box starts, lower_corner + c * voxel, as in `geometry.voxel_mesh`; the default
      -voxel / 2 is the region frame of 10 cm cells made by rounding, so vertices come back in that frame.
    chunk: decoder queries per call (memory bound; results do not depend on it).
    min_area: connected pieces with less area (m^2) are dropped; pinhole_edges: boundary loops with at most
      this many edges are closed (0: none).
    points / sensors: input points and sensor positions (output frame): observed faces (`observed_vertices`)
      face the nearest sensor, and each connected piece follows its observed faces; pieces nobody saw face
      away from their own centre (outwards from what they enclose), or up. Without points: the latter.
    fair: near-horizontal surfaces are faired between the input points (`hgca_core.geometry.fairing`: the
      generated ground between scan rings is flattened onto what the rings say, and the decoder's local bias at
      the rings taken out); needs `points`.
    tree: a `geometry.nearest.PointIndex` of `points` when the caller has one (`pipeline.complete_local` builds
      one per completion for the fairing's anchors and the vertices' observed_distance); None: built here if needed.
    workers: threads for the numpy steps (default: torch's thread count, the decoder's).
    timings: if given, filled with the wall seconds of each step (decode, extract, clean, fair) and the CPU seconds
      (`*_cpu`, all threads of this process: on a busy machine a fairer measure of the work).
    """
    import time

    from hgca_core.geometry import mesh_clean as mc
    from hgca_core.geometry.udf_surface import dual_surface

    workers = torch.get_num_threads() if workers is None else max(1, int(workers))
    t0, c0 = time.perf_counter(), time.process_time()
    shift = np.asarray(-voxel / 2 if lower_corner is None else lower_corner, dtype=np.float64) + voxel / 2
    g, vals = udf_grid(decoder, cells, latents, voxel, res, chunk)
    t1, c1 = time.perf_counter(), time.process_time()
    surf = dual_surface(g, vals, res, voxel, workers=workers)
    v, f = surf.vertices * res + shift, surf.faces
    t2, c2 = time.perf_counter(), time.process_time()
    observed = None
    if points is not None and sensors is not None and len(points) and len(v):
        observed = observed_vertices(v, points, voxel)
    v, f = mc.clean_surface(v, f, min_area, observed, sensors, pinhole_edges, workers)
    t3, c3 = time.perf_counter(), time.process_time()
    if fair and points is not None and len(points) and len(f):
        from hgca_core.geometry.fairing import fair_ground
        from hgca_core.geometry.nearest import PointIndex

        tree = PointIndex(points) if tree is None else tree
        v = fair_ground(v, f, workers=workers, points=tree)[0]   # anchors: the ground vertices' nearest points
    if timings is not None:   # wall seconds, and CPU seconds of this process (all its threads)
        t4, c4 = time.perf_counter(), time.process_time()
        timings.update(decode=t1 - t0, extract=t2 - t1, clean=t3 - t2, fair=t4 - t3,
                       decode_cpu=c1 - c0, extract_cpu=c2 - c1, clean_cpu=c3 - c2, fair_cpu=c4 - c3)
    return trimesh.Trimesh(vertices=v, faces=f, process=False)


def observed_vertices(vertices: np.ndarray, points: np.ndarray, voxel: float) -> np.ndarray:
    """(V,) bool: the vertex lies in a `voxel` cell (by rounding, like the 10 cm input cells) that holds an input
    point, i.e. within ~0.9 voxel of one; a search among the points' sorted cell keys, several times cheaper than a
    nearest-neighbour query."""
    if len(points) == 0 or len(vertices) == 0:
        return np.zeros(len(vertices), dtype=bool)
    keys = np.unique(pack(np.round(np.asarray(points, dtype=np.float64) / voxel).astype(np.int64)))
    q = pack(np.round(np.asarray(vertices, dtype=np.float64) / voxel).astype(np.int64))
    return keys[np.minimum(np.searchsorted(keys, q), len(keys) - 1)] == q


def finish_mesh(mesh: trimesh.Trimesh, observed_distance: np.ndarray | None = None,
                split: float = OBSERVED_SPLIT) -> trimesh.Trimesh:
    """Add what a scene builder expects to a finished mesh (in its final frame): per-vertex normals as the
    vertex attributes `nx`, `ny`, `nz` (and trimesh's `vertex_normals`), `observed_distance` when given, and
    the face attribute `material` (uint8: 0 observed, 1 generated: the mean observed_distance of the face's
    vertices above `split` metres; all 0 without distances)."""
    from hgca_core.geometry.mesh_clean import vertex_normals

    v, f = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    normals = vertex_normals(v, f) if len(v) else np.zeros((0, 3), np.float32)
    out = trimesh.Trimesh(vertices=v, faces=f, vertex_normals=normals if len(v) else None, process=False)
    if observed_distance is not None:
        d = np.asarray(observed_distance, dtype=np.float32)
        out.vertex_attributes["observed_distance"] = d
        material = (d[f].mean(1) > split).astype(np.uint8) if len(f) else np.zeros(0, np.uint8)
    else:
        material = np.zeros(len(f), np.uint8)
    for name, k in (("nx", 0), ("ny", 1), ("nz", 2)):
        out.vertex_attributes[name] = normals[:, k]
    out.face_attributes["material"] = material
    return out


def decimate(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """The mesh with at most `max_faces` triangles, by quadric edge collapse (fast-simplification).

    Quadric error keeps detail where the surface bends and spends few triangles on flat facades and roads, most
    of a street (a default region's 1.8 M -> 1 M moves the surface by < 1 mm, benchmarks/results/mesh_quality).
    Open borders are kept as they are (collapsing them shrinks holes' rims and splits pieces) unless the limit
    cannot be met otherwise. Vertex attributes are dropped: the vertices are new (`finish_mesh` adds them).
    """
    import fast_simplification

    if max_faces < 1:
        raise ValueError(f"max_faces must be at least 1, got {max_faces}")
    n = len(mesh.faces)
    if n <= max_faces:
        return mesh
    v, f = interruptible(fast_simplification.simplify, np.asarray(mesh.vertices, dtype=np.float32),
                         np.asarray(mesh.faces, dtype=np.int32), target_count=max_faces, preserve_border=True)
    if len(f) > max_faces:   # mostly border (small or ragged pieces): the limit wins over the borders
        v, f = interruptible(fast_simplification.simplify, v, f, target_count=max_faces)
    return trimesh.Trimesh(vertices=v.astype(np.float64), faces=f.astype(np.int64), process=False)


def interruptible(fn: Callable[..., tuple[np.ndarray, ...]], *args: object, **kwargs: object) -> tuple[np.ndarray, ...]:
    """`fn(*args, **kwargs)` (arrays in, a tuple of arrays out) in a forked child when the CLI's signal handler
    is installed: fast-simplification holds the GIL for seconds (a default region's mesh: ~4 s), and Python runs
    signal handlers only between bytecodes of the main thread, so Ctrl-C or SIGTERM waited for it. Here the
    main thread waits on a pipe, where a signal is handled at once, and the handler's last words kill the child.
    Without fork (Windows) or the handler (a library caller), it is a plain call."""
    import os
    import signal

    from hgca_core import interrupt

    if not hasattr(os, "fork") or not interrupt.installed():
        return fn(*args, **kwargs)
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: compute, send the arrays, end without Python's exit handlers
        code = 1
        try:
            os.close(read_end)
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, signal.SIG_DFL)
            out = fn(*args, **kwargs)
            with os.fdopen(write_end, "wb") as pipe:
                pipe.write(len(out).to_bytes(4, "little"))
                for a in out:
                    np.save(pipe, np.asarray(a), allow_pickle=False)
            code = 0
        finally:
            os._exit(code)
    os.close(write_end)
    with interrupt.last_words(lambda _signum: os.kill(pid, signal.SIGKILL)):
        try:
            with os.fdopen(read_end, "rb") as pipe:
                count = int.from_bytes(pipe.read(4), "little")
                out = tuple(np.load(pipe, allow_pickle=False) for _ in range(count))
        except (OSError, ValueError, EOFError):
            out = None
        finally:
            _, status = os.waitpid(pid, 0)
    if out is None or status != 0:   # the child failed (memory?): the same call here says why
        return fn(*args, **kwargs)
    return out


def udf_surface_points(decoder: object, cells: np.ndarray | torch.Tensor, latents: torch.Tensor | None = None,
                       lower_corner: float | np.ndarray | None = None, voxel: float = 0.1, res: float = 0.05,
                       threshold: float | None = None, chunk: int = 1 << 15, project: int = 0) -> np.ndarray:
    """Grid points "close to the surface": res-grid points with unsigned distance below `threshold` (paper, App.:
    5 cm cells with implicit distance below 0.5, in units of the 10 cm voxel, i.e. 5 cm).

    The default threshold is voxel / 2: res / 2 would miss a plane lying midway between two grid planes (its
    nearest grid points are exactly res / 2 away). With `project` the points are moved onto the zero level,
    which gives surface samples for Chamfer distances rather than the band the paper's IoU uses.
    """
    threshold = 0.5 * voxel if threshold is None else float(threshold)
    shift = np.asarray(-voxel / 2 if lower_corner is None else lower_corner, dtype=np.float64) + voxel / 2
    g, vals = udf_grid(decoder, cells, latents, voxel, res, chunk)
    p = g[vals < threshold].astype(np.float64) * res
    if project and len(p):
        p = project_to_zero(_as_field(decoder, _cells_tensor(cells), latents), p, steps=project, max_dist=voxel * 0.999)
    return p + shift

"""Decimation: a mesh light enough to ship (`limit_faces`, `decimate`), interruptible while it runs."""
from __future__ import annotations

from typing import Callable

import numpy as np
import trimesh

def limit_faces(mesh: trimesh.Trimesh, max_faces: int | None, note: Callable[[str], None] | None = None
                ) -> trimesh.Trimesh:
    """The completion's triangle limit: `decimate` to `max_faces` when the mesh has more (None or 0 keeps every
    triangle), telling `note` first, since a default region's mesh takes seconds."""
    if not max_faces or len(mesh.faces) <= max_faces:
        return mesh
    if note is not None:
        note(f"simplifying {len(mesh.faces)} faces")
    return decimate(mesh, max_faces)


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

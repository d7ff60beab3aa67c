"""Who runs the tiles: in this process, one after another, or as Ray tasks on a local or existing cluster.

Both run the same plan with the same `tile.complete_tile` and hand every result to the driver's callback, in
the order tiles finish. A phase-two tile needs its neighbours' coarse cells: in-process they are simply ready
(phase one runs first); on Ray the phase-two task gets the phase-one tasks' cell outputs as ObjectRefs, so Ray
starts it when both are done. Ray retries a task whose worker died (`MAX_RETRIES`); its result reaches the
driver once, and the driver writes it once, under its content key.
"""
from __future__ import annotations

import logging
import os
import signal
import threading
from collections import Counter, deque
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from hgca_core.errors import HgcaError, InputError
from hgca_core.tiling.tile import TileJob, cells_of, complete_tile

MAX_RETRIES = 3
OBJECT_STORE_BYTES = 512 * 2**20   # local Ray: tile results are tens of MB; Ray spills to disk beyond this
NeighbourCells = tuple[tuple, list[np.ndarray]]   # (region tuple, coarse cells per sample)


@dataclass
class Pending:
    """A tile to run: its job, its scans' indices, and the tiles (by index) whose cells it is conditioned on,
    with the cells of those that finished before this run."""

    job: TileJob
    conditioned_on: tuple[int, ...]
    ready_cells: dict[int, NeighbourCells]


class LocalRunner:
    """Tiles in this process, phase one before phase two (the order of `pending`)."""

    name = "local"

    def run(self, pending: list[Pending], scans: list, on_result: Callable[[dict], None],
            on_start: Callable[[int], None] | None = None,
            on_step: Callable[[int, str, int, int], None] | None = None) -> None:
        """`on_step(index, stage, step, total)`: each chain step of the tile running (its coarse, fine and mesh
        stages), so a bar moves within a tile of a minute or more, not only between tiles."""
        made: dict[int, NeighbourCells] = {}
        for p in pending:
            if on_start:
                on_start(p.job.index)
            cells = {**p.ready_cells, **made}
            neighbours = [cells[j] for j in p.conditioned_on]
            result = complete_tile(p.job, [scans[i] for i in p.job.scans], neighbours,
                                   _tile_steps(on_step, p.job.index))
            made[p.job.index] = (p.job.region, cells_of(result))
            on_result(result)


def _tile_steps(on_step: Callable[[int, str, int, int], None] | None, index: int) -> Callable | None:
    """The pipeline's progress callback (stage, step, total, message, sample) as `on_step` for tile `index`."""
    if on_step is None:
        return None

    def report(stage: str, step: int, total: int, *_: object) -> None:
        on_step(index, stage, step, total)

    return report


def tile_task(job: TileJob, n_scans: int, *inputs) -> tuple[dict, NeighbourCells]:
    """The Ray task: `inputs` are the tile's `DriveScan`s then its neighbours' cells (top-level arguments, so Ray
    resolves their ObjectRefs, waiting for the phase-one tasks that make them). Returns the result and, as a
    second object for the phase-two tasks that depend on it, the cells alone."""
    result = complete_tile(job, list(inputs[:n_scans]), list(inputs[n_scans:]))
    return result, (job.region, cells_of(result))


def require_ray():
    """The ray module, or an InputError saying how to get it (checked before a drive writes anything)."""
    try:
        import ray
    except ImportError:
        raise InputError("Ray is not installed: `pip install 'hgca[ray]'`, or run with --workers 1 "
                         "(the same plan in this process)") from None
    return ray


class RayRunner:
    """Tiles as Ray tasks with their memory declared (so a node never takes more tiles than fit), on a Ray
    started in this process (`workers` CPUs' worth of tiles at `threads` torch threads each) or on the cluster
    at `address`."""

    name = "ray"

    def __init__(self, workers: int, threads: int, memory: float, address: str | None = None) -> None:
        self.ray = ray = require_ray()
        self.threads = threads
        self.memory = memory
        self.started = False
        self._previous: dict = {}
        if not ray.is_initialized():
            before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
            kwargs: dict = {"include_dashboard": False, "log_to_driver": False, "logging_level": logging.WARNING,
                            "configure_logging": True}
            if address:
                try:
                    ray.init(address=address, **kwargs)
                except (ConnectionError, TimeoutError) as exc:
                    raise InputError(f"cannot reach the Ray cluster at {address} ({exc}); a cluster with token "
                                     "authentication (Ray's default) also needs RAY_AUTH_MODE=token and its token "
                                     "(RAY_AUTH_TOKEN or ~/.ray/auth_token) here") from None
            else:
                root = str(Path(__file__).resolve().parents[2])   # workers import this hgca_core, not another
                path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH", "")) if p)
                ray.init(num_cpus=workers * threads, object_store_memory=OBJECT_STORE_BYTES,
                         runtime_env={"env_vars": {"PYTHONPATH": path, "OMP_NUM_THREADS": str(threads)}}, **kwargs)
            self.started = True
            self._take_signals(before)
        largest = max((n["Resources"].get("memory", 0.0) for n in ray.nodes() if n.get("Alive")), default=0.0)
        if largest < memory:
            self.close()
            raise InputError(f"a tile needs about {memory / 2**30:.1f} GiB, the largest Ray node offers "
                             f"{largest / 2**30:.1f} GiB: use smaller tiles (--size) or bigger nodes")

    def run(self, pending: list[Pending], scans: list, on_result: Callable[[dict], None],
            on_start: Callable[[int], None] | None = None,
            on_step: Callable[[int, str, int, int], None] | None = None) -> None:
        """`scans`: the drive's `inputs.DriveScan`s; `on_start` and `on_step` are not called (Ray decides when a
        task starts, and its steps run in a worker).

        Tasks are submitted along the drive, at most `in_flight` at a time, and the driver lets go of every
        object as soon as no task still to be submitted needs it: a scan once its last tile is submitted, a
        phase-one tile's cells once its phase-two neighbours are, a result once `on_result` has it. So the object
        store holds the few tiles in flight, not the drive: a worker reads its inputs from and writes its results
        to the same few shared pages, tile after tile. Were every result kept referenced until the drive's end,
        each tile would land on pages of the store no worker had touched yet, and a worker's resident memory
        would grow by about a result and its new scans a tile."""
        ray = self.ray
        task = ray.remote(tile_task).options(num_cpus=self.threads, memory=int(self.memory), num_returns=2,
                                             max_retries=MAX_RETRIES, retry_exceptions=False)
        scan_uses = Counter(i for p in pending for i in p.job.scans)
        cell_uses = Counter(j for p in pending for j in p.conditioned_on)
        scan_refs: dict[int, object] = {}
        cell_refs: dict[int, object] = {}
        # along the drive, each phase-two tile right after the later of its neighbours (phase one and two in
        # turn), so a scan's last task comes soon after its first: Ray starts a task once its inputs exist
        queue = deque(sorted(pending, key=lambda p: (max((p.job.index, *p.conditioned_on)),
                                                     bool(p.conditioned_on))))
        waiting: list = []
        limit = self.in_flight()

        def submit(p: Pending) -> None:
            for i in p.job.scans:
                if i not in scan_refs:
                    scan_refs[i] = ray.put(scans[i])
            for j in p.conditioned_on:
                if j not in cell_refs:         # finished before this run: its cells came from the cache
                    cell_refs[j] = ray.put(p.ready_cells[j])
            inputs = [scan_refs[i] for i in p.job.scans] + [cell_refs[j] for j in p.conditioned_on]
            result_ref, cells_ref = task.remote(p.job, len(p.job.scans), *inputs)
            if cell_uses[p.job.index]:
                cell_refs[p.job.index] = cells_ref
            waiting.append(result_ref)
            for uses, refs, keys in ((scan_uses, scan_refs, p.job.scans), (cell_uses, cell_refs, p.conditioned_on)):
                for k in keys:                 # the submitted task holds what it needs until it has run
                    uses[k] -= 1
                    if not uses[k]:
                        refs.pop(k, None)

        while queue or waiting:
            while queue and len(waiting) < limit:
                submit(queue.popleft())
            done, waiting = ray.wait(waiting, num_returns=1)
            try:
                result = ray.get(done[0])
            except ray.exceptions.RayTaskError as exc:
                cause = getattr(exc, "cause", None)
                if isinstance(cause, HgcaError):
                    raise cause from None
                raise
            del done
            on_result(result)
            del result

    def in_flight(self) -> int:
        """How many tasks to have submitted at once: two per tile the cluster can run at a time (by CPUs), so a
        worker that finishes finds its next task's inputs already in the store."""
        cpus = float(self.ray.cluster_resources().get("CPU", 1.0))
        return max(2, 2 * int(cpus // max(1, self.threads)))

    def _take_signals(self, before: dict) -> None:
        """ray.init replaces the SIGTERM handler with one that aborts the process (exit 134, a crash report):
        take SIGINT and SIGTERM back, stop the Ray this process started, then do what was done `before` (the
        CLI's one-line exit 130 / 143, or Python's KeyboardInterrupt / termination)."""
        if threading.current_thread() is not threading.main_thread():
            return
        self._previous = before

        def handler(signum: int, frame) -> None:
            self.close()
            previous = before.get(signum)
            if callable(previous):
                previous(signum, frame)
            else:
                signal.signal(signum, signal.SIG_DFL)
                os.kill(os.getpid(), signum)

        for sig in before:
            signal.signal(sig, handler)

    def close(self) -> None:
        if self.started:
            self.started = False
            self.ray.shutdown()
            if threading.current_thread() is threading.main_thread():
                for sig, previous in self._previous.items():
                    signal.signal(sig, previous if previous is not None else signal.SIG_DFL)

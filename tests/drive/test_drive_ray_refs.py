"""The Ray runner lets go of each object once no task still to be submitted needs it, so what the object store
holds (and with it the shared pages each Ray worker touches) follows the tiles in flight, not the drive's length.

A stand-in for the `ray` module runs the runner's real bookkeeping without a cluster: its ObjectRefs are plain
objects, a submitted task holds its inputs until it has run (as Ray does), and a weak reference to every object
put or returned tells what is still alive whenever the driver gets a result."""
from __future__ import annotations

import weakref
from types import SimpleNamespace

import numpy as np
import pytest

from hgca_core.tiling.plan import neighbours
from hgca_core.tiling.runners import Pending, RayRunner


class Ref:
    """An ObjectRef: the object store's entry stays while this is referenced."""

    def __init__(self, value, kind: str) -> None:
        self.value, self.kind = value, kind


class FakeRay:
    """Just enough of `ray` for `RayRunner.run`: put, remote tasks with two returns, wait (which runs the oldest
    submitted task), get; it records a weak reference to every object it hands out."""

    exceptions = SimpleNamespace(RayTaskError=RuntimeError)

    def __init__(self, cpus: int = 2) -> None:
        self.cpus = cpus
        self.made: list[weakref.ref] = []
        self.queue: list[tuple] = []           # submitted tasks: (inputs, result ref, cells ref)

    def _ref(self, value, kind: str) -> Ref:
        r = Ref(value, kind)
        self.made.append(weakref.ref(r))
        return r

    def alive(self, kind: str) -> int:
        return sum(1 for w in self.made if w() is not None and w().kind == kind)

    def cluster_resources(self) -> dict:
        return {"CPU": float(self.cpus)}

    def put(self, value) -> Ref:
        return self._ref(value, "scan" if isinstance(value, SimpleNamespace) else "cells")

    def remote(self, fn):
        fake = self

        class Task:
            def options(self, **kwargs):
                return self

            def remote(self, job, n_scans, *inputs):
                result = fake._ref(None, "result")
                cells = fake._ref(None, "cells")
                fake.queue.append((job, list(inputs), result, cells))
                return result, cells

        return Task()

    def wait(self, refs: list, num_returns: int = 1):
        job, inputs, result, cells = self.queue.pop(0)   # runs: its inputs are released when it is done
        assert all(isinstance(r, Ref) for r in inputs)
        result.value = {"index": job.index, "samples": [{"cells": np.zeros((1, 3), np.int16)}]}
        cells.value = (job.region, [np.zeros((1, 3), np.int16)])
        del inputs
        return [result], [r for r in refs if r is not result]

    def get(self, ref: Ref):
        return ref.value


def plan(tiles: int, scans_per_tile: int = 5, stride: int = 4) -> tuple[list[Pending], list]:
    """A drive of `tiles` tiles along a line of scans, phase one (even tiles) first, odd ones conditioned on
    their neighbours: the order `tiling.run._pending` gives."""
    scans = [SimpleNamespace(i=i) for i in range(stride * tiles + scans_per_tile)]
    jobs = [SimpleNamespace(index=i, scans=tuple(range(stride * i, stride * i + scans_per_tile)), region=(i,))
            for i in range(tiles)]
    order = sorted(jobs, key=lambda j: (j.index % 2, j.index))
    return [Pending(j, neighbours(j.index, tiles) if j.index % 2 else (), {}) for j in order], scans


def held_per_result(tiles: int) -> list[dict]:
    """For each result the driver gets: how many scans, cells and results the object store still holds."""
    ray = FakeRay()
    runner = object.__new__(RayRunner)
    runner.ray, runner.threads, runner.memory = ray, 1, 1.0
    seen: list[dict] = []
    pending, scans = plan(tiles)
    runner.run(pending, scans, lambda result: seen.append({k: ray.alive(k) for k in ("scan", "cells", "result")}))
    assert len(seen) == tiles
    assert not ray.queue and ray.alive("scan") == ray.alive("result") == 0, "nothing held once the run is over"
    return seen


@pytest.mark.parametrize("kind", ["scan", "cells", "result"])
def test_objects_held_follow_the_tiles_in_flight_not_the_drive(kind):
    short, long = held_per_result(8), held_per_result(40)
    assert max(s[kind] for s in long) == max(s[kind] for s in short), \
        f"the store holds more {kind} objects at once on a longer drive: {max(s[kind] for s in long)}"


def test_results_are_released_once_handed_on():
    # 2 CPUs at 1 thread a tile: 4 tasks in flight, so at most 4 results (the one being handed on among them)
    assert max(s["result"] for s in held_per_result(40)) <= 4

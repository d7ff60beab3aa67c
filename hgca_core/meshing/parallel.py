"""Vectorised numpy steps split over threads.

Most numpy kernels (fancy indexing, arithmetic, einsum, sorting) release the GIL, so contiguous slices of one
vectorised step run side by side on the cores the caller was given: on 2 cores a slice-wise step takes ~0.55x
its one-thread time (benchmarks/results/meshing_time.md). The caller passes the thread count (the
pipeline passes torch's, so a Ray worker with 1 thread per tile stays on its one core).
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Callable, TypeVar

T = TypeVar("T")

# below this many elements a slice is not worth a thread (the hand-off costs ~0.1 ms)
MIN_SLICE = 1 << 15


def slices(n: int, workers: int) -> list[tuple[int, int]]:
    """[0, n) cut into at most `workers` contiguous (start, stop) ranges of near-equal size (at least one)."""
    parts = max(1, min(int(workers), n // MIN_SLICE))
    bounds = [n * k // parts for k in range(parts + 1)]
    return list(zip(bounds[:-1], bounds[1:]))


def map_slices(fn: Callable[[int, int], T], n: int, workers: int = 1) -> list[T]:
    """[fn(start, stop) for each of `slices(n, workers)`], in order; run in threads when there is more than one."""
    parts = slices(n, workers)
    if len(parts) == 1:
        return [fn(*parts[0])]
    with ThreadPoolExecutor(len(parts)) as pool:
        return list(pool.map(lambda p: fn(*p), parts))


def run_all(*fns: Callable[[], object], workers: int = 1) -> list[object]:
    """Results of independent calls `fns`, run side by side in up to `workers` threads (in order without)."""
    if workers <= 1 or len(fns) == 1:
        return [fn() for fn in fns]
    with ThreadPoolExecutor(min(workers, len(fns))) as pool:
        return list(pool.map(lambda fn: fn(), fns))

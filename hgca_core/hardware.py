"""What this process runs on: the torch device a user asked for, and names of the hardware for records.

Shared by training (the run record names the device it actually used), `hgca bench` (result files) and the
commands that take `--device`; it sits outside both so that training never imports the benchmark code.
"""
from __future__ import annotations

import ctypes
import functools
import os
import platform
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from hgca_core.errors import InputError

if TYPE_CHECKING:
    import torch


# glibc's mallopt parameter (<malloc.h>), our value, and the variables by which a user tunes glibc's allocator at
# start-up (any of them set: `tune_allocator` leaves the allocator alone).
M_ARENA_MAX = -8
ALLOCATOR = {M_ARENA_MAX: 1}
ALLOCATOR_ENV = ("MALLOC_ARENA_MAX", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")
# `HGCA_ALLOCATOR=system` keeps glibc's defaults (for A/B measurements, or a user who preloads another allocator).
ALLOCATOR_SWITCH = "HGCA_ALLOCATOR"


@functools.cache
def glibc() -> ctypes.CDLL | None:
    """This process's glibc (for `mallopt` and `malloc_trim`), or None off Linux, on another C library, or where it
    cannot be loaded. The one check behind `tune_allocator` and `release_free_memory`."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        if not os.confstr("CS_GNU_LIBC_VERSION").startswith("glibc"):
            return None
        return ctypes.CDLL("libc.so.6")
    except (ValueError, OSError):
        return None


def allocator_tunable() -> bool:
    """Whether `tune_allocator` may act: glibc on Linux, not switched off, no MALLOC_* tuning of the user's own."""
    if os.environ.get(ALLOCATOR_SWITCH, "") == "system" or any(k in os.environ for k in ALLOCATOR_ENV):
        return False
    return glibc() is not None


def tune_allocator() -> bool:
    """Make glibc serve every thread from one arena; True if it took effect. Call it before the process starts
    threads (the CLI does, before any command imports torch).

    Why: glibc gives each new thread an arena of its own (up to 8 per core), and torch's OpenMP threads free
    blocks there that the other threads never reuse, so they pile up. One arena took the median peak RSS of a
    default-region full completion from 2.50 to 2.29 GiB (40 x 120 m: 4.38 to 4.04 GiB) at the same time, measured
    in fresh processes, interleaved (`benchmarks/completion_ab.py allocator`; its pages are in git at 7f06b18).
    Keeping freed blocks (a 64 MiB mmap threshold) also cut the full stage's ~4.5 million page faults to ~1 million
    and its time by a sixth, but took the peak past the 2.7 GiB budget in some runs
    (the allocator grid in git at 7f06b18), so it is not set; nor are torch's 2 MiB pages
    (`THP_MEM_ALLOC_ENABLE`: 0.55 M faults, the time within the spread, +0.18 GiB). Results do
    not change, only where memory comes from. Only one-shot processes call this: the CLI (and with it the Blender
    add-on's jobs) and the bench worker; Ray's workers keep glibc's defaults."""
    if not allocator_tunable():
        return False
    mallopt = glibc().mallopt
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return all([bool(mallopt(param, value)) for param, value in ALLOCATOR.items()])


def release_free_memory() -> bool:
    """Hand the heap's free pages back to the system (glibc's `malloc_trim(0)`); False where there is no glibc.

    Why: glibc returns a freed block to the system only if it was mapped on its own (large) or lies at the top of
    the heap; the holes a stage's many mid-sized tensors leave stay resident. `pipeline.complete_local` calls this
    where a stage's working set has just died (before the fine stage and before meshing): the full stage's median
    peak RSS fell from 2.26 to 2.03 GiB on the default region and from 3.96 to 3.62 GiB on 40 x 120 m, at a few
    seconds of re-faulted pages (`benchmarks/results/trim_full*.md`, in git at 7f06b18). It changes no setting, so a host process
    (Blender, a notebook) loses nothing but pages it had freed."""
    libc = glibc()
    if libc is None:
        return False
    trim = libc.malloc_trim
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    trim(0)
    return True


def peak_rss_bytes() -> int:
    """This process's own peak resident set (VmHWM). Not getrusage's ru_maxrss: on Linux that also holds the
    resident set of the process that spawned this one at the moment of the spawn (vfork + exec), so a worker
    started by a large parent would report the parent's memory."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    import resource

    scale = 1 if sys.platform == "darwin" else 1024        # bytes on macOS, KiB elsewhere
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale


def cpu_name() -> str:
    """The CPU model ('AMD EPYC 9454 48-Core Processor'), or what `platform` knows where /proc is absent."""
    info = Path("/proc/cpuinfo")
    if info.exists():
        for line in info.read_text(errors="replace").splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def resolve_device(name: str, local_rank: int | None = None) -> "torch.device":
    """`--device` as a torch.device: 'cpu', 'cuda' or 'cuda:N'. Under torchrun (`local_rank` given) a bare
    'cuda' means this rank's own GPU, cuda:LOCAL_RANK. Unknown names and a CUDA request on a machine (or torch
    build) without a GPU are input errors, not tracebacks."""
    import torch

    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError):
        raise InputError(f"--device must be cpu, cuda or cuda:N, not {name!r}") from None
    if dev.type not in ("cpu", "cuda"):
        raise InputError(f"--device must be cpu, cuda or cuda:N, not {name!r}")
    if dev.type == "cpu":
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise InputError(f"--device {name} asked for, but this torch build sees no CUDA GPU")
    index = dev.index if dev.index is not None else (local_rank if local_rank is not None else torch.cuda.current_device())
    if index >= torch.cuda.device_count():
        raise InputError(f"--device {name}: GPU {index} asked for, but only {torch.cuda.device_count()} visible")
    return torch.device("cuda", index)


def device_name(device: "torch.device") -> str:
    """The hardware behind a torch device: the GPU's name for CUDA, the CPU model for the CPU."""
    import torch

    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return cpu_name()


def machine() -> dict:
    """CPU, visible cores, torch and Python versions, date, and the first GPU when there is one."""
    import torch

    info = {"cpu": cpu_name(), "cores": len(os.sched_getaffinity(0)), "torch": torch.__version__,
            "threads": torch.get_num_threads(), "python": platform.python_version(),
            "date": time.strftime("%Y-%m-%d %H:%M")}
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    return info

"""What this process runs on: the torch device a user asked for, and names of the hardware for records.

Shared by training (the run record names the device it actually used), `hgca bench` (result files) and the
commands that take `--device`; it sits outside both so that training never imports the benchmark code.
"""
from __future__ import annotations

import os
import platform
import time
from pathlib import Path
from typing import TYPE_CHECKING

from hgca_core.errors import InputError

if TYPE_CHECKING:
    import torch


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

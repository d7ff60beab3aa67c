"""Set up hgca_core for the add-on: a venv with hgca's wheel and torch, then a check that it really runs.

    BASE_PYTHON install_core.py install --env DIR --wheel hgca-X.whl [--wheels FOLDER] [--torch cpu|cuda]
                                        [--torch-index URL] [--log FILE]
    CORE_PYTHON install_core.py check

This file runs outside Blender (no bpy), started by the add-on's *Install Core* as a background process; it
speaks the add-on's progress records (`{"protocol": 1, "stage": ..., "step", "total", "message"}`, one JSON line
each on stdout) so `core.Job` can show it, cancel it and read its result. The venv is built in `DIR.new` and only
replaces `DIR` once the check passed, so a cancelled or failed install leaves the previous core as it was.
`--wheels FOLDER` is the offline path: pip then reads nothing but that folder (and hgca's wheel).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

PROTOCOL = 1
TORCH = "torch==2.13.0"
TORCH_CPU_INDEX = "https://download.pytorch.org/whl/cpu"
EXTRAS = "real,recordings"  # pyarrow: Argoverse 2 logs; rosbags, pye57, kiss-icp: ROS bags, E57, odometry
# pip prints one "Collecting" line per distribution: about this many for hgca[real,recordings] and torch
EXPECTED_PACKAGES = 60


# pip is silent while it unpacks (torch alone: about a minute): a heartbeat record every HEARTBEAT_S seconds keeps
# the bar moving, along an expected INSTALL_S seconds (never past its end)
HEARTBEAT_S = 2.0
INSTALL_S = 120.0
_PRINT = threading.Lock()


def record(stage: str, step: int = 0, total: int = 1, message: str = "", **extra) -> None:
    line = json.dumps({"protocol": PROTOCOL, "stage": stage, "step": step, "total": total, "message": message,
                       "sample": 0, "samples": 1, **extra})
    with _PRINT:
        print(line, flush=True)


def plain(text: str, count: int) -> str:
    """What a line of pip's output means to a Blender user (the raw line stays in the log): retries become a word
    about the network, package lines say how far the list is."""
    low = text.lower()
    if "retrying" in low and ("connection" in low or "retry(" in low or "timed out" in low):
        return "the network is slow or interrupted: pip is retrying (details in the install log)"
    if text.startswith(("Collecting ", "Processing ", "Requirement already")):
        name = text.split()[1] if len(text.split()) > 1 else ""
        return f"collecting packages ({count} of about {EXPECTED_PACKAGES}): {Path(name).name[:60]}"
    if text.startswith("Downloading "):
        parts = text.split()
        size = " ".join(parts[2:])[:40] if len(parts) > 2 else ""
        return f"downloading {Path(parts[1]).name[:60] if len(parts) > 1 else ''} {size}".strip()
    if text.startswith("Installing collected packages"):
        return "installing the packages (torch takes about a minute)"
    return text[:200]


def venv_python(env: Path) -> Path:
    """The interpreter inside a venv (Scripts\\python.exe on Windows)."""
    return env / ("Scripts/python.exe" if os.name == "nt" else "bin/python")


def pip_args(wheel: Path, wheels: Path | None, torch: str, torch_index: str) -> list[str]:
    """`pip install` arguments: hgca's wheel with its extras and torch; offline from `wheels` when given."""
    args = ["install", "--progress-bar", "off", "--no-input", "--disable-pip-version-check",
            f"{wheel}[{EXTRAS}]", TORCH]
    if wheels is not None:
        return [*args, "--no-index", "--find-links", str(wheels), "--find-links", str(wheel.parent)]
    if torch_index:
        args += ["--extra-index-url", torch_index]
    return args


def run_logged(cmd: list[str], log, stage: str, counter: list[int] | None = None) -> None:
    """Run `cmd`, copying its output to the log and each line to a progress record; raise on failure."""
    log.write(f"$ {' '.join(cmd)}\n")
    log.flush()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                            text=True, errors="replace", bufsize=1)
    tail: list[str] = []
    assert proc.stdout is not None
    unpacking = threading.Event()
    done = threading.Event()

    def heartbeat() -> None:
        unpacking.wait()
        start = time.monotonic()
        while not done.wait(HEARTBEAT_S):
            elapsed = time.monotonic() - start
            step = min(int(elapsed), int(INSTALL_S) - 1)
            record("install", step, int(INSTALL_S), f"installing the packages: {elapsed:.0f} s "
                                                    "(torch takes about a minute)")

    beat = threading.Thread(target=heartbeat, daemon=True)
    beat.start()
    try:
        for line in proc.stdout:
            text = line.rstrip()
            log.write(text + "\n")
            log.flush()
            if not text:
                continue
            tail = (tail + [text])[-20:]
            if counter is not None and text.startswith("Installing collected packages"):
                stage = "install"  # unpacking: no count, but the longest part (torch)
                unpacking.set()
            if stage == "pip" and counter is not None and text.startswith(("Collecting ", "Processing ",
                                                                            "Requirement already")):
                counter[0] += 1
            step = min(counter[0], EXPECTED_PACKAGES) if counter is not None and stage == "pip" else 0
            record(stage, step, EXPECTED_PACKAGES if stage == "pip" else 1,
                   plain(text, counter[0] if counter is not None else 0))
    finally:
        done.set()
        unpacking.set()
    if proc.wait() != 0:
        errors = [t for t in tail if "error" in t.lower()] or tail[-1:]
        raise RuntimeError(f"{Path(cmd[0]).name} {cmd[1] if len(cmd) > 1 else ''} failed (exit {proc.returncode}): "
                           f"{errors[-1] if errors else 'no output'}")


def install(env: Path, wheel: Path, wheels: Path | None, torch: str, torch_index: str, log_path: Path) -> Path:
    new = env.with_name(env.name + ".new")
    shutil.rmtree(new, ignore_errors=True)
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "w", encoding="utf-8") as log:
        log.write(f"base python {sys.executable} {sys.version.split()[0]}\n")
        record("venv", 0, 1, f"creating the environment with Python {sys.version.split()[0]}")
        run_logged([sys.executable, "-m", "venv", str(new)], log, "venv")
        record("venv", 1, 1, "environment created")
        python = venv_python(new)
        counter = [0]
        run_logged([str(python), "-m", "pip", *pip_args(wheel, wheels, torch, torch_index)], log, "pip", counter)
        record("check", 0, 1, "importing torch and hgca_core, loading the shipped weights")
        run_logged([str(python), str(Path(__file__).resolve()), "check"], log, "check")
        record("check", 1, 1, "the core works")
    old = env.with_name(env.name + ".old")
    shutil.rmtree(old, ignore_errors=True)
    if env.exists():
        env.rename(old)
    new.rename(env)  # a venv's interpreter finds its packages through pyvenv.cfg next to it: moving is safe
    shutil.rmtree(old, ignore_errors=True)
    return venv_python(env)


def check() -> dict:
    """Import torch and hgca_core and load the shipped weights on the CPU: what a completion needs first."""
    import torch  # noqa: F401  (the import itself is the check)

    import hgca_core
    from hgca_core.pipeline import load_models

    load_models("full", None, None, "cpu")
    version = getattr(hgca_core, "__version__", "")
    return {"python": sys.executable, "hgca": version, "torch": torch.__version__,
            "cuda": bool(torch.cuda.is_available())}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="install_core.py", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    i = sub.add_parser("install")
    i.add_argument("--env", required=True)
    i.add_argument("--wheel", required=True)
    i.add_argument("--wheels", default=None)
    i.add_argument("--torch", choices=("cpu", "cuda"), default="cpu")
    i.add_argument("--torch-index", default=None, help="extra index for torch (cpu default: PyTorch's CPU index)")
    i.add_argument("--log", default=None)
    sub.add_parser("check")
    args = p.parse_args(argv)
    if args.command == "check":
        try:
            print(json.dumps(check()))
        except Exception as exc:  # the message is the answer: what is missing or broken
            print(f"error: {exc.__class__.__name__}: {exc}", file=sys.stderr)
            return 2
        return 0
    env = Path(args.env)
    index = args.torch_index if args.torch_index is not None else (TORCH_CPU_INDEX if args.torch == "cpu" else "")
    try:
        python = install(env, Path(args.wheel), Path(args.wheels) if args.wheels else None, args.torch, index,
                         Path(args.log) if args.log else env.with_name("install.log"))
    except Exception as exc:
        shutil.rmtree(env.with_name(env.name + ".new"), ignore_errors=True)
        record("error", message=str(exc))
        return 2
    record("done", outputs=[str(python)])
    return 0


if __name__ == "__main__":
    sys.exit(main())

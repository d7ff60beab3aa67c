"""`hgca` command line. Each subcommand lives in hgca_core/commands/<name>.py with
`add_arguments(parser)` and `run(args) -> int`; modules are imported only when their command runs,
so `hgca info` does not pay for importing torch."""
from __future__ import annotations

if __name__ == "__main__":  # `python -m hgca_core.cli`: take over Ctrl-C before the imports below
    from hgca_core import interrupt as _interrupt

    _interrupt.install()

import argparse
import errno
import importlib
import os
import sys
import traceback
import warnings

from hgca_core import __version__, interrupt
from hgca_core.errors import HgcaError, HgcaWarning
from hgca_core.hardware import tune_allocator

COMMANDS = {
    "info": "print point count, bounds and attributes of scan files",
    "read": "read scans (any supported format, optional poses) and write them accumulated to one .npz",
    "synth": "make synthetic street scenes with simulated LiDAR (one scene, or a dataset split)",
    "train": "train a model stage with a time budget, resuming from its checkpoint",
    "region": "print the default region `complete` would use for these scans (--region form, or --json)",
    "complete": "complete LiDAR scans into meshes",
    "drive": "complete a whole drive tile by tile along its trajectory (resumable, parallel on Ray)",
    "eval": "evaluate completion on the synthetic test split against baselines",
    "eval-real": "score completions of real scans without ground truth (height cut, observed free space)",
    "poses": "write the poses JSON of a sequence folder (KITTI, Argoverse 2, nuScenes), or estimate the poses of "
             "scans that have none (--estimate: LiDAR odometry)",
    "bench": "measure time and memory of completion per stage",
    "demo": "complete the bundled example and render it",
}


DEBUG_ENV = "HGCA_DEBUG"
EPILOG = (f"Bad input ends a command with one 'hgca CMD: error: ...' line and exit status 2, and nothing is "
          f"written. Set {DEBUG_ENV}=1 to also print the Python traceback of an unexpected failure (for a bug "
          "report).")


def build_parser(argv: list[str]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="hgca", epilog=EPILOG,
                                     description="LiDAR scene extrapolation with hierarchical Generative Cellular "
                                                 "Automata (hGCA)")
    parser.add_argument("--version", action="version", version=f"hgca {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, help_text in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=f"hgca_core.commands.{name.replace('-', '_')}")
        module = _load(name, argv)
        if module is not None:
            module.add_arguments(p)
    return parser


def _load(name: str, argv: list[str]):
    """Import a command module only when argv names it (keeps start-up light), else None."""
    return importlib.import_module(f"hgca_core.commands.{name.replace('-', '_')}") if argv[:1] == [name] else None


# OpenMP threads that busy-wait between parallel regions steal the cores of every other process: on a shared
# 2-core machine (or beside Blender) a 2-thread decode took 21.7 s busy-waiting, 5.1 s with PASSIVE
# (benchmarks/mesh_quality.py). The variable is read once, when torch loads its OpenMP runtime, so it is
# set before any command imports torch; a value the user set wins.
OMP_DEFAULTS = {"OMP_WAIT_POLICY": "PASSIVE"}
# Every command but `train` runs with glibc's allocator set up by `hardware.tune_allocator` (one arena): measured on
# completions (`benchmarks/results/allocator_*.md`). Training keeps glibc's defaults: it was not measured with the
# setting, and every recipe's step times so far were taken without it.


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    _hold_closed_descriptors()
    if "torch" not in sys.modules:
        for key, value in OMP_DEFAULTS.items():
            os.environ.setdefault(key, value)
    if argv[:1] != ["train"]:
        tune_allocator()
    previous = interrupt.install(argv[0] if argv[:1] and argv[0] in COMMANDS else "")
    stderr, sys.stderr = sys.stderr, _Survivor(sys.stderr)
    try:
        return _main(argv)
    finally:
        sys.stderr = stderr
        interrupt.restore(previous)


class _Survivor:
    """stderr that outlives its reader (`hgca drive ... 2>&1 | head -1`): once a write fails on the closed pipe,
    the descriptor points at /dev/null and later writes (progress bars, warnings) are dropped, so the command
    finishes its work and writes its outputs instead of ending on a BrokenPipeError with exit 0 and nothing."""

    def __init__(self, stream) -> None:
        self._stream = stream
        self._lost = False

    def write(self, text: str) -> int:
        if not self._lost:
            try:
                return self._stream.write(text)
            except (BrokenPipeError, ValueError):   # the reader left; ValueError: a closed file object
                self._lose()
        return len(text)

    def flush(self) -> None:
        if not self._lost:
            try:
                self._stream.flush()
            except (BrokenPipeError, ValueError):
                self._lose()

    def _lose(self) -> None:
        self._lost = True
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, self._stream.fileno())
            os.close(devnull)
        except (OSError, ValueError, AttributeError):   # no descriptor (a test's buffer)
            pass

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def _hold_closed_descriptors() -> None:
    """A standard descriptor the caller closed (`>&-`) gets /dev/null, so that no file the command opens (a mesh
    being written) takes descriptor 1 and receives what a library prints. `sys.stdout` stays None: progress
    records then know they have no reader (`progress.Progress` says so on stderr and the work goes on). A closed
    stderr becomes /dev/null: progress bars and warnings then have somewhere to go."""
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:
            try:
                held = os.open(os.devnull, os.O_RDWR)
                if held != fd:
                    os.dup2(held, fd)
                    os.close(held)
            except OSError:
                return
    if sys.stderr is None:   # closed by the caller: messages go nowhere, as asked, instead of onto stdout
        sys.stderr = open(os.devnull, "w", encoding="utf-8")


def _main(argv: list[str]) -> int:
    args = build_parser(argv).parse_args(argv)
    module = importlib.import_module(args._module)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", HgcaWarning)
            warnings.showwarning = _one_line_warning(args.command, warnings.showwarning)
            return int(module.run(args) or 0)
    except BrokenPipeError:  # `hgca info ... | head` closed the pipe: not an error
        sys.stderr.close()
        return 0
    except HgcaError as exc:
        print(f"hgca {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # raised by code that handles SIGINT itself (the trainer's second Ctrl-C)
        print(f"hgca {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001  (anything unforeseen is still one line, not a traceback)
        if os.environ.get(DEBUG_ENV, "") not in ("", "0"):
            traceback.print_exc()
        print(f"hgca {args.command}: error: {unexpected(exc)}", file=sys.stderr)
        return 2


def unexpected(exc: BaseException) -> str:
    """The one line for a failure no check foresaw: what the OS or Python said, and how to see more."""
    if isinstance(exc, MemoryError):
        return "out of memory: this input needs more memory than the machine (or its limit) allows"
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        where = f" ({exc.filename})" if exc.filename else ""
        return f"no space left on the device{where}; nothing was written"
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return (f"unexpected {type(exc).__name__}{': ' + text if text else ''} "
            f"(set {DEBUG_ENV}=1 for the traceback)")


def _one_line_warning(command: str, default):
    """`hgca CMD: warning: ...` for our own warnings; library warnings keep Python's format."""
    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, HgcaWarning):
            if sys.stderr is not None:   # closed (`2>&-`): never onto stdout, which may carry JSON lines
                print(f"hgca {command}: warning: {message}", file=sys.stderr)
        else:
            default(message, category, filename, lineno, file, line)
    return show


if __name__ == "__main__":
    sys.exit(main())

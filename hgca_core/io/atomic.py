"""Atomic file writes: a temp file in the target's folder, fsync, then `os.replace`.

A crash or Ctrl-C mid-write never leaves a half-written mesh where the Blender add-on (or a later run)
would pick it up as finished output. `AtomicBatch` extends this to several files that belong together (the
k samples of one completion): all are written to temp files first and moved into place in one short commit,
so an interrupted run leaves either every output or none of them.

Temp files being written are registered in `_PENDING`, so the CLI's signal handler (`hgca_core.interrupt`),
which ends the process with `os._exit`, can remove them first; a signal that arrives during a commit is held
back until the commit is over (`defer_signal`).

A SIGKILL (or a power cut) leaves no chance to clean up: its temp files stay. Their names hold the writer's
pid (`temp_prefix`), so the next write of the same target removes those whose writer is gone
(`remove_stale`), and never one that a live run is writing.
"""
from __future__ import annotations

import contextlib
import errno
import os
import re
import signal
import tempfile
from typing import Any, BinaryIO, Callable

from hgca_core.errors import InputError

_PENDING: set[str] = set()  # temp files written but not yet moved into place
_COMMIT = {"depth": 0, "deferred": 0}  # commits in progress; a signal number held back until they end


def _default_mode() -> int:
    """Permissions an ordinary `open(path, "w")` would give (mkstemp's 0600 would hide outputs from others)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def discard_pending() -> None:
    """Remove every temp file not yet moved into place (the signal handler calls this before exiting)."""
    for tmp in list(_PENDING):
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        _PENDING.discard(tmp)


def defer_signal(signum: int) -> bool:
    """True (and the signal is kept for later) when a commit is moving files into place right now."""
    if _COMMIT["depth"] > 0:
        _COMMIT["deferred"] = _COMMIT["deferred"] or signum
        return True
    return False


def temp_prefix(path: str | os.PathLike) -> str:
    """The start of the name of every temp file written for `path`: `.<name>.<pid>.` (the suffix is `.tmp`)."""
    return f".{os.path.basename(os.fspath(path))}.{os.getpid()}."


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return True
    return True


def remove_stale(path: str | os.PathLike) -> list[str]:
    """Remove the temp files of `path` (same folder and target name) whose writing process no longer exists;
    returns their paths. Temp files of other targets, and of live processes, are left alone."""
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    own = re.compile(re.escape(f".{os.path.basename(path)}.") + r"(\d+)\.[A-Za-z0-9_]+\.tmp")
    removed = []
    try:
        names = os.listdir(directory)
    except OSError:
        return removed
    for name in names:
        m = own.fullmatch(name)
        if m is None or int(m.group(1)) == os.getpid() or _alive(int(m.group(1))):
            continue
        with contextlib.suppress(OSError):
            os.unlink(os.path.join(directory, name))
            removed.append(os.path.join(directory, name))
    return removed


class _Guarded:
    """The temp file as the writer sees it: after a failed write (disk full) every further call is a no-op, so
    a library object that still holds it (numpy's ZipFile, freed later) cannot fail a second time on a closed
    file ("seek of closed file") after the one clear error."""

    def __init__(self, f: BinaryIO) -> None:
        self._f = f
        self.failed = False

    def _call(self, name: str, *args: Any) -> Any:
        if self.failed:
            return 0
        try:
            return getattr(self._f, name)(*args)
        except (OSError, ValueError):
            self.failed = True
            raise

    def write(self, data: Any) -> int:
        return self._call("write", data)

    def seek(self, *args: Any) -> int:
        return self._call("seek", *args)

    def tell(self) -> int:
        return self._call("tell")

    def flush(self) -> None:
        self._call("flush")

    def truncate(self, *args: Any) -> int:
        return self._call("truncate", *args)

    def close(self) -> None:
        """The file is closed by `_stage`, not by the writer."""

    def __getattr__(self, name: str) -> Any:
        return getattr(self._f, name)


def _stage(path: str, write: Callable[[BinaryIO], None]) -> str:
    """Write `path`'s content to a registered temp file next to it; returns the temp file's path."""
    directory = os.path.dirname(os.path.abspath(path))
    try:
        os.makedirs(directory, exist_ok=True)
        remove_stale(path)
        fd, tmp = tempfile.mkstemp(dir=directory, prefix=temp_prefix(path), suffix=".tmp")
    except OSError as exc:
        raise InputError(f"cannot write output ({_reason(exc)})", path) from None
    _PENDING.add(tmp)
    guarded = None
    try:
        with os.fdopen(fd, "wb") as f:
            guarded = _Guarded(f)
            write(guarded)  # type: ignore[arg-type]
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, _default_mode())
    except BaseException as exc:
        if guarded is not None:
            guarded.failed = True
        _drop(tmp)
        if isinstance(exc, OSError):
            raise InputError(f"cannot write output ({_reason(exc)}); nothing was written", path) from None
        raise
    return tmp


def _reason(exc: OSError) -> str:
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return "no space left on the device"
    return str(exc.strerror or exc)


def _drop(tmp: str) -> None:
    with contextlib.suppress(OSError):
        os.unlink(tmp)
    _PENDING.discard(tmp)


def _commit(staged: list[tuple[str, str]]) -> None:
    """Move every staged temp file into place; SIGINT/SIGTERM wait until all are moved."""
    _COMMIT["depth"] += 1
    try:
        for i, (tmp, path) in enumerate(staged):
            try:
                os.replace(tmp, path)
            except OSError as exc:
                for rest, _ in staged[i:]:
                    _drop(rest)
                raise InputError(f"cannot write output ({exc.strerror or exc})", path) from None
            _PENDING.discard(tmp)
    finally:
        _COMMIT["depth"] -= 1
        deferred = _COMMIT["deferred"]
        if _COMMIT["depth"] == 0 and deferred:
            _COMMIT["deferred"] = 0
            signal.raise_signal(deferred)


def atomic_write(path: str | os.PathLike, write: Callable[[BinaryIO], None]) -> str:
    """Call `write(f)` on a temp file next to `path`, then move it into place; returns the path."""
    path = os.fspath(path)
    _commit([(_stage(path, write), path)])
    return path


class AtomicBatch:
    """Files that appear together or not at all: `add()` writes each to a temp file, `commit()` moves them
    all into place; leaving the `with` block by an exception removes the temp files and writes nothing."""

    def __init__(self) -> None:
        self._staged: list[tuple[str, str]] = []

    def add(self, path: str | os.PathLike, write: Callable[[BinaryIO], None]) -> str:
        path = os.fspath(path)
        self._staged.append((_stage(path, write), path))
        return path

    def commit(self) -> list[str]:
        staged, self._staged = self._staged, []
        _commit(staged)
        return [path for _, path in staged]

    def discard(self) -> None:
        for tmp, _ in self._staged:
            _drop(tmp)
        self._staged = []

    def __enter__(self) -> "AtomicBatch":
        return self

    def __exit__(self, *exc_info) -> None:
        self.discard()

"""Atomic file writes: a temp file in the target's folder, fsync, then `os.replace`.

A crash or Ctrl-C mid-write never leaves a half-written mesh where the Blender add-on (or a later run)
would pick it up as finished output.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from typing import BinaryIO, Callable

from hgca_core.errors import InputError


def _default_mode() -> int:
    """Permissions an ordinary `open(path, "w")` would give (mkstemp's 0600 would hide outputs from others)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def atomic_write(path: str | os.PathLike, write: Callable[[BinaryIO], None]) -> str:
    """Call `write(f)` on a temp file next to `path`, then move it into place; returns the path."""
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    try:
        os.makedirs(directory, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=directory, prefix=f".{os.path.basename(path)}.", suffix=".tmp")
    except OSError as exc:
        raise InputError(f"cannot write output ({exc.strerror})", path) from None
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, _default_mode())
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise InputError(f"cannot write output ({exc.strerror or exc})", path) from None
        raise
    return path

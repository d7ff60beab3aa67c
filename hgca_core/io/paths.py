"""Paths checked before any work starts: inputs are readable regular files (or say what they are instead),
outputs are never an input and always a writable file in an existing folder.

`hgca complete a_s0.ply -o a.ply` names its first sample `a_s0.ply`, and `hgca read g.npz -o g.npz` names
its input: both silently replaced the input once the run finished. An output is the same file as an input
when their resolved paths agree (symlinks, `..`) or, for files that exist, when they share device and inode
(hard links). Folders are probed by creating a temp file in them, the one test that also holds for root,
read-only mounts and ACLs; finding this out after minutes of inference loses the run.
"""
from __future__ import annotations

import contextlib
import errno
import os
import stat
import tempfile
from typing import Iterable

from hgca_core.errors import InputError


def check_readable(path: str, what: str = "file") -> None:
    """Raise `InputError` saying what `path` is when it is not a non-empty regular file: missing, a folder,
    a symbolic link loop or a dangling link, a device or pipe, empty, or not readable."""
    try:
        st = os.stat(path)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise InputError(f"{what} is a symbolic link loop", path) from None
        if os.path.islink(path):
            raise InputError(f"{what} is a symbolic link to a missing target ({os.readlink(path)})", path) from None
        if exc.errno == errno.ENOENT:
            raise InputError(f"{what} not found", path) from None
        raise InputError(f"cannot open {what} ({exc.strerror})", path) from None
    except ValueError as exc:  # NUL bytes in the name
        raise InputError(f"{what} name is not a valid path ({exc})", path) from None
    if stat.S_ISDIR(st.st_mode):
        raise InputError(f"{what} is a folder, not a regular file", path)
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{what} is not a regular file (a device, pipe or socket)", path)
    if st.st_size == 0:
        raise InputError(f"{what} is empty (0 bytes)", path)
    if not os.access(path, os.R_OK):
        raise InputError(f"{what} is not readable (permission denied)", path)


def _identity(path: str) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino


def check_outputs(outputs: Iterable[str | os.PathLike], inputs: Iterable[str | os.PathLike | None]) -> None:
    """Raise `InputError` naming the output when it is an input, a folder, or cannot be written."""
    by_path: dict[str, str] = {}
    by_inode: dict[tuple[int, int], str] = {}
    for item in inputs:
        if item is None:
            continue
        path = os.fspath(item)
        by_path[os.path.realpath(path)] = path
        ident = _identity(path)
        if ident is not None:
            by_inode[ident] = path
    probed: set[str] = set()
    for item in outputs:
        out = os.fspath(item)
        hit = by_path.get(os.path.realpath(out))
        ident = _identity(out)
        if hit is None and ident is not None:
            hit = by_inode.get(ident)
        if hit is not None:
            same = "" if hit == out else f" (the input {hit})"
            raise InputError(f"output would overwrite an input file{same}; choose another output name", out)
        if os.path.isdir(out):
            raise InputError("output is an existing folder; give a file name", out)
        folder = os.path.dirname(out) or "."  # not normalised: the OS resolves `missing/..` and fails
        if folder in probed:
            continue
        if not os.path.isdir(folder):
            what = "is not a folder" if os.path.exists(folder) else "does not exist"
            raise InputError(f"output folder {what}", folder)
        try:
            fd, probe = tempfile.mkstemp(dir=folder, prefix=".hgca-write-test-")
        except OSError as exc:
            raise InputError(f"cannot write in the output folder ({exc.strerror})", folder) from None
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(probe)
        probed.add(folder)

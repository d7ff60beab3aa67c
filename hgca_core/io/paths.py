"""Paths checked before any work starts: inputs are readable regular files (or say what they are instead),
outputs are never an input and always a writable file in an existing folder.

`hgca complete a_s0.ply -o a.ply` names its first sample `a_s0.ply`, and `hgca read g.npz -o g.npz` names
its input: both silently replaced the input once the run finished. An output is the same file as an input
when their resolved paths agree (symlinks, `..`) or, for files that exist, when they share device and inode
(hard links). A folder given as input (a sequence) stands for every file under it: `hgca poses SEQ -o
SEQ/poses.json` would replace the poses the folder itself holds. Each output is probed by creating the very
temp file its atomic write will create (`hgca_core.io.atomic.temp_prefix`), the one test that also holds for
root, read-only mounts, ACLs and names too long for the file system; finding this out after minutes of
inference loses the run.
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


MAX_FOLDER_FILES = 200_000  # files of an input folder looked at (a sequence has thousands, not millions)


def _folder_files(folder: str, skip: set[str]) -> Iterable[str]:
    """The files under an input folder, not descending into `skip` (real paths: a drive folder inside it)."""
    seen = 0
    for dirpath, dirnames, filenames in os.walk(folder):
        dirnames[:] = [d for d in dirnames if os.path.realpath(os.path.join(dirpath, d)) not in skip]
        for name in filenames:
            seen += 1
            if seen > MAX_FOLDER_FILES:
                return
            yield os.path.join(dirpath, name)


def check_outputs(outputs: Iterable[str | os.PathLike], inputs: Iterable[str | os.PathLike | None],
                  skip: Iterable[str | os.PathLike] = ()) -> None:
    """Raise `InputError` naming the output when it is an input (or a file of an input folder), a folder, or
    cannot be written: the one check every command's outputs pass before any work. `skip`: folders inside an
    input folder whose files are not inputs (a drive folder kept beside its sequence)."""
    outputs = [os.fspath(o) for o in outputs]
    skipped = {os.path.realpath(os.fspath(s)) for s in skip}
    by_path: dict[str, str] = {}
    by_inode: dict[tuple[int, int], str] = {}

    def add(path: str, label: str) -> None:
        by_path[os.path.realpath(path)] = label
        ident = _identity(path)
        if ident is not None:
            by_inode[ident] = label

    for item in inputs:
        if item is None:
            continue
        path = os.fspath(item)
        try:
            folder = os.path.isdir(path)
        except ValueError:
            folder = False
        if folder:
            for f in _folder_files(path, skipped):
                add(f, f"a file of the input folder {path}")
        add(path, path)
    for out in outputs:
        try:
            hit = by_path.get(os.path.realpath(out))
        except ValueError as exc:  # NUL bytes in the name
            raise InputError(f"output name is not a valid path ({exc})", out) from None
        ident = _identity(out)
        if hit is None and ident is not None:
            hit = by_inode.get(ident)
        if hit is not None:
            same = "" if hit == out else f" ({hit if hit.startswith('a file of') else 'the input ' + hit})"
            raise InputError(f"output would overwrite an input file{same}; choose another output name", out)
        if os.path.isdir(out):
            raise InputError("output is an existing folder; give a file name", out)
        folder = os.path.dirname(out) or "."  # not normalised: the OS resolves `missing/..` and fails
        if not os.path.isdir(folder):
            what = "is not a folder" if os.path.exists(folder) else "does not exist"
            raise InputError(f"output folder {what}", folder)
        probe_output(out)


def probe_output(out: str) -> None:
    """Create and remove the temp file the atomic write of `out` will create, or say why it cannot be."""
    from hgca_core.io.atomic import temp_prefix

    folder = os.path.dirname(out) or "."
    try:
        fd, probe = tempfile.mkstemp(dir=folder, prefix=temp_prefix(out), suffix=".tmp")
    except OSError as exc:
        if exc.errno == errno.ENAMETOOLONG:
            raise InputError(f"output name is too long for the file system ({len(os.path.basename(out))} "
                             "characters, and its temp file while writing needs about 20 more); choose a shorter "
                             "name", out) from None
        raise InputError(f"cannot write in the output folder ({exc.strerror})", folder) from None
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(probe)


def check_output_folder(folder: str | os.PathLike, inputs: Iterable[str | os.PathLike | None] = (),
                        what: str = "output folder") -> None:
    """Refuse an output folder that is an existing file, an input (or holds one), has a name too long for the
    file system, or cannot be created or written; probes by creating (and removing) a folder in it or in its
    nearest existing parent."""
    root = os.path.abspath(os.fspath(folder))
    if os.path.exists(root) and not os.path.isdir(root):
        raise InputError(f"{what} exists and is not a folder", os.fspath(folder))
    real = os.path.realpath(root)
    for item in inputs:
        if item is not None and os.path.realpath(os.fspath(item)) == real:
            raise InputError(f"{what} is an input ({os.fspath(item)}); choose another folder", os.fspath(folder))
    missing, parent = [], root
    while not os.path.exists(parent):
        missing.append(os.path.basename(parent))
        parent = os.path.dirname(parent)
    if not os.path.isdir(parent):
        raise InputError(f"{what} lies under a file, not a folder", parent)
    limit = os.pathconf(parent, "PC_NAME_MAX") if hasattr(os, "pathconf") else 255
    for name in missing:
        if len(name.encode()) > limit:
            raise InputError(f"{what} name is too long for the file system ({len(name)} characters, at most "
                             f"{limit})", os.fspath(folder))
    try:
        os.rmdir(tempfile.mkdtemp(dir=parent, prefix=".hgca-write-test-"))
    except OSError as exc:
        raise InputError(f"cannot create or write the {what} here ({exc.strerror})", parent) from None

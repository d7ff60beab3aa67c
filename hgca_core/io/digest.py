"""sha256 of files: how a drive's tiles and a distilled run's teacher name the weights they were made with, so
a file changed under the same path is caught rather than silently used."""
from __future__ import annotations

import hashlib
import os
from functools import lru_cache
from pathlib import Path

from hgca_core.errors import InputError


def file_digest(path: str | os.PathLike) -> str:
    """sha256 of a file, cached per (path, mtime, size) so a worker hashes its weights once."""
    p = Path(path)
    try:
        st = p.stat()
    except OSError:
        raise InputError("file not found", str(p)) from None
    return _digest(str(p.resolve()), st.st_mtime_ns, st.st_size)


@lru_cache(maxsize=16)
def _digest(path: str, mtime: int, size: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()

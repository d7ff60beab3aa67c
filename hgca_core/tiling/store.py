"""A drive's folder: finished tiles under their content key, the tile meshes people open, and drive.json.

    DIR/cache/<key>.npz      one finished tile, all samples (written atomically, once: the commit record that
                             makes a tile finished; a re-run with the same inputs, weights, seed and settings
                             finds it and skips the tile)
    DIR/tiles/<i>_s<k>.ply   tile i, sample k: the part of it the tile owns (exported from the cache entry)
    DIR/drive_s<k>.ply       the merged drive, sample k
    DIR/drive.json           the plan, scans, tiles (regions, seeds, keys, status, timings, worker) and status
    DIR/.lock                held (an OS file lock) by the one run writing the folder; the OS drops the lock
                             when that process ends in any way, so a crashed run never leaves it stuck

Meshes are in world coordinates; the writers keep georeferenced ones exact (`hgca_core.io.georef`).
"""
from __future__ import annotations

import json
import os
import socket
import zipfile
from pathlib import Path

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.atomic import atomic_write

FORMAT = 1


class DriveStore:
    """The files of one drive folder."""

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)
        self.cache = self.root / "cache"
        self.tiles = self.root / "tiles"
        self._lock_fd: int | None = None

    def check(self) -> None:
        """Refuse an --out that cannot be a drive folder, before anything is read or written."""
        if self.root.exists() and not self.root.is_dir():
            raise InputError("output exists and is not a folder", str(self.root))

    def check_creatable(self) -> None:
        """For a folder not made yet: its names fit the file system and its nearest existing parent takes it."""
        from hgca_core.io.paths import check_output_folder

        check_output_folder(self.root, what="drive folder")

    def prepare(self) -> None:
        """Create the folders, take the folder's lock (`lock`), then remove the temp files a killed run left in
        them (only our own `.*.tmp`: no other run can be writing them now)."""
        self.check()
        for d in (self.root, self.cache, self.tiles):
            try:
                d.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise InputError(f"cannot create output folder ({exc.strerror})", str(d)) from None
        self.lock()
        for d in (self.root, self.cache, self.tiles):
            for tmp in d.glob(".*.tmp"):
                tmp.unlink(missing_ok=True)

    def lock(self) -> None:
        """Hold DIR/.lock for this process, or refuse (InputError, exit 2) while another run holds it. An OS lock
        (flock; msvcrt on Windows), not a pid file: it goes with its process, however that ends, and a pid
        that was reused cannot fake it. The file says who holds it, for the message."""
        if self._lock_fd is not None:
            return
        path = self.root / ".lock"
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            raise InputError(f"cannot create the drive's lock file ({exc.strerror})", str(path)) from None
        if not _try_lock(fd):
            try:
                holder = os.read(fd, 200).decode(errors="replace").strip() or "another process"
            finally:
                os.close(fd)
            raise InputError(f"another hgca drive is writing this folder ({holder}): wait for it to end or stop "
                             "it, or choose another --out", str(self.root))
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()} on {socket.gethostname()}".encode())
        self._lock_fd = fd

    def unlock(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)            # closing the descriptor drops the lock
            self._lock_fd = None

    def entry(self, key: str) -> Path:
        return self.cache / f"{key}.npz"

    def has(self, key: str) -> bool:
        return self.entry(key).is_file()

    def damaged(self, key: str) -> str:
        """'' when the entry is missing or readable (its arrays and record open), else what is wrong with it."""
        path = self.entry(key)
        if not path.is_file():
            return ""
        try:
            with zipfile.ZipFile(path) as z:
                bad = z.testzip()
                if bad is None:
                    with z.open("meta.npy") as f:
                        meta = json.loads(str(np.lib.format.read_array(f, allow_pickle=False)))
                    bad = None if isinstance(meta, dict) and isinstance(meta.get("samples"), list) else "meta"
            if bad is not None:
                return f"a damaged member {bad}"
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            return f"{type(exc).__name__}: {exc}"
        return ""

    def discard(self, key: str) -> None:
        """Remove a damaged entry so the tile is computed and saved again."""
        self.entry(key).unlink(missing_ok=True)

    def save(self, result: dict) -> Path:
        """Write a tile result under its key (atomically; an existing entry is the same content and is kept)."""
        path = self.entry(result["key"])
        if path.exists():
            return path
        arrays: dict[str, np.ndarray] = {}
        meta = {k: v for k, v in result.items() if k != "samples"}
        meta["samples"] = []
        for k, s in enumerate(result["samples"]):
            for name in ("vertices", "faces", "observed_distance", "cells"):
                arrays[f"s{k}_{name}"] = s[name]
            meta["samples"].append({"seed": s["seed"], "fixed_cells": s["fixed_cells"],
                                   "free_cells": s.get("free_cells")})
        arrays["meta"] = np.array(json.dumps(meta))
        atomic_write(path, lambda f: np.savez(f, **arrays))
        return path

    def load(self, key: str, only: int | None = None) -> dict:
        """A finished tile's result, as `complete_tile` returned it; with `only`, the arrays of that sample alone
        (the others' are None), so merging sample k does not hold every sample of every tile."""
        path = self.entry(key)
        names = ("vertices", "faces", "observed_distance", "cells")
        try:
            with np.load(path, allow_pickle=False) as z:
                meta = json.loads(str(z["meta"]))
                samples = []
                for k, s in enumerate(meta["samples"]):
                    wanted = only is None or k == only
                    samples.append({**s, **{n: z[f"s{k}_{n}"] if wanted else None for n in names}})
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            raise InputError(f"finished tile is unreadable ({exc}); delete it to recompute the tile", str(path)) \
                from None
        meta["samples"] = samples
        return meta

    def tile_mesh(self, index: int, sample: int, ext: str = ".ply") -> Path:
        return self.tiles / f"{index}_s{sample}{ext}"

    def drive_mesh(self, sample: int, ext: str = ".ply") -> Path:
        return self.root / f"drive_s{sample}{ext}"

    @property
    def manifest(self) -> Path:
        return self.root / "drive.json"

    def read_manifest(self) -> dict | None:
        """The previous run's drive.json, or None (missing or unreadable: a run that died while writing it
        cannot have, since it is written atomically, but a user may have edited it)."""
        try:
            doc = json.loads(self.manifest.read_text())
        except (OSError, ValueError):
            return None
        return doc if isinstance(doc, dict) and doc.get("format") == FORMAT else None

    def write_manifest(self, doc: dict) -> None:
        text = json.dumps({"format": FORMAT, **doc}, indent=1)
        atomic_write(self.manifest, lambda f: f.write(text.encode()))


def _try_lock(fd: int) -> bool:
    """Take an exclusive lock on the open file without waiting; False when another process holds it."""
    try:
        import fcntl
    except ImportError:                                    # Windows
        import msvcrt

        try:
            msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
        except OSError:
            return False
        return True
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return False
    return True

"""A drive's folder: finished tiles under their content key, the tile meshes people open, and drive.json.

    DIR/cache/<key>.npz      one finished tile, all samples, and what it was made from (written atomically,
                             once: the commit record that makes a tile finished; a re-run with the same inputs,
                             weights, seed and settings finds it, checks it (`check_entry`) and skips the tile)
    DIR/tiles/<i>_s<k>.ply   tile i, sample k: the part of it the tile owns (exported from the cache entry)
    DIR/drive_s<k>.ply       the merged drive, sample k
    DIR/drive.json           the plan, scans, tiles (regions, seeds, keys, what each was made from, the sha256
                             of its files, status, timings, worker) and status; checked when read (`records`)
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
_ANEW = "writing a new one; every cached tile is checked on its own and its meshes are written again"
ARRAYS = ("vertices", "faces", "observed_distance", "cells")   # per sample, `s<k>_<name>` in a cache entry


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

    def relative(self, path: Path) -> str:
        """A path in DIR as drive.json names it (`tiles/0_s0.ply`)."""
        return Path(path).relative_to(self.root).as_posix()

    def check_entry(self, key: str, made_from: dict, samples: int, sha256: str | None) -> tuple[str, str]:
        """('', its sha256) when the entry under `key` can be reused: it reads whole, it was made for this tile
        (its key and `made_from`; entries of older versions carry the key alone), every sample's mesh is whole
        (faces index its vertices), and it matches the sha256 its drive.json record gives (when there is one).
        Else (what is wrong, '')."""
        from hgca_core.tiling.records import sha256_file

        path = self.entry(key)
        try:
            digest = sha256_file(path)
            with np.load(path, allow_pickle=False) as z:
                meta = json.loads(str(z["meta"]))
                problem = _check_meta(meta, key, made_from, samples)
                for k in range(samples if not problem else 0):
                    problem = _check_sample(k, {n: z[f"s{k}_{n}"] for n in ARRAYS})
                    if problem:
                        break
        except (OSError, ValueError, KeyError, EOFError, RecursionError, zipfile.BadZipFile) as exc:
            return f"is unreadable ({type(exc).__name__}: {exc})", ""
        if problem:
            return problem, ""
        if sha256 is not None and sha256 != digest:
            return "does not match its checksum in drive.json (cut short, or another file copied over it?)", ""
        return "", digest

    def discard(self, key: str) -> None:
        """Remove a damaged entry so the tile is computed and saved again."""
        self.entry(key).unlink(missing_ok=True)

    def save(self, result: dict, made_from: dict | None = None) -> Path:
        """Write a tile result under its key (atomically; an existing entry is the same content and is kept),
        with what it was made from (`records.made_from`), so that a resumed run can tell it is this tile's."""
        path = self.entry(result["key"])
        if path.is_file():
            return path
        arrays: dict[str, np.ndarray] = {}
        meta = {k: v for k, v in result.items() if k != "samples"}
        if made_from is not None:
            meta["made_from"] = made_from
        meta["samples"] = []
        for k, s in enumerate(result["samples"]):
            for name in ARRAYS:
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
        names = ARRAYS
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
        """The previous run's drive.json, or None when there is none or it cannot be trusted: not JSON, another
        format, or a field a resume reads missing or of another type than the drive writes (`records.
        check_record`; a user may have edited it). An untrusted record is said in one warning naming the key;
        the run then checks every cached tile on its own and writes a new record."""
        from hgca_core.tiling.records import check_record, warn

        try:
            text = self.manifest.read_text()
        except FileNotFoundError:
            return None
        except (OSError, UnicodeDecodeError) as exc:
            warn(f"{self.manifest}: unreadable ({exc}): {_ANEW}")
            return None
        try:
            doc = json.loads(text)
        except (ValueError, RecursionError) as exc:
            warn(f"{self.manifest}: not JSON ({exc}; cut short or edited?): {_ANEW}")
            return None
        problem = check_record(doc)
        if problem:
            warn(f"{self.manifest}: {problem} (edited by hand?): {_ANEW}")
            return None
        if doc["format"] != FORMAT:
            warn(f"{self.manifest}: format {doc['format']}, not {FORMAT} (another hgca version's): {_ANEW}")
            return None
        return doc

    def write_manifest(self, doc: dict) -> None:
        text = json.dumps({"format": FORMAT, **doc}, indent=1)
        atomic_write(self.manifest, lambda f: f.write(text.encode()))


def _check_meta(meta, key: str, made_from: dict, samples: int) -> str:
    """'' when a cache entry's record says it is the result of this tile with `samples` samples."""
    if not isinstance(meta, dict) or not isinstance(meta.get("samples"), list):
        return "is unreadable (its record is not a tile's)"
    if meta.get("key") != key:
        return f"was made for another tile (its key is {str(meta.get('key'))[:12]}...: another drive's or plan's?)"
    if "made_from" in meta and meta["made_from"] != made_from:
        return "was made from other inputs or settings than this tile's"
    if len(meta["samples"]) != samples:
        return f"has {len(meta['samples'])} samples, not {samples}"
    if not all(isinstance(s, dict) and isinstance(s.get("fixed_cells"), int) for s in meta["samples"]):
        return "is unreadable (its samples' record is damaged)"
    if "made_from" in meta and [s.get("seed") for s in meta["samples"]] != [made_from["seed"] + k
                                                                             for k in range(samples)]:
        return "has samples of other seeds than this tile's"
    return ""


def _check_sample(k: int, a: dict[str, np.ndarray]) -> str:
    """'' when sample k's arrays make a mesh (faces index its vertices) with a distance per vertex and cells."""
    v, f, d, c = (a[n] for n in ARRAYS)
    if not (v.ndim == 2 and v.shape[1] == 3 and v.dtype.kind == "f" and np.isfinite(v).all()):
        return f"has damaged vertices (sample {k}: shape {v.shape}, {v.dtype})"
    if not (f.ndim == 2 and f.shape[1] == 3 and f.dtype.kind in "iu"):
        return f"has damaged faces (sample {k}: shape {f.shape}, {f.dtype})"
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        worst = int(f.max()) if f.max() >= len(v) else int(f.min())
        return f"has faces that index past its vertices (sample {k}: index {worst}, {len(v)} vertices)"
    if d.shape != (len(v),) or d.dtype.kind != "f":
        return f"has a damaged observed_distance (sample {k}: shape {d.shape}, {len(v)} vertices)"
    if not (c.ndim == 2 and c.shape[1] == 3 and c.dtype.kind in "iu"):
        return f"has damaged cells (sample {k}: shape {c.shape}, {c.dtype})"
    return ""


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

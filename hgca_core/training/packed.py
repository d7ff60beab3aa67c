"""Packed coarse training samples: the 20 cm cell sets the coarse stage trains on (the input s^0, the ground truth,
the observed free space) and, in val and test splits, the visible cells its validation scores, as bit grids.

Why: a GPU machine is reached with a copy of the repository and at most 64 MiB beside it, and cannot build scenes
itself (no Embree there, and its minutes are better spent training). A full sample is ~6 MB (points, surfaces,
distance pairs, evaluation scans); packed, a scene is ~60 kB, so several hundred travel with the repository. The
full samples stay the one source: a packed file is derived from one by `pack_sample` and gives the coarse stage
the very cells its source gives (`training.data` reads both); the fine stage and `hgca eval` need the full files.
"""
from __future__ import annotations

import json
import shutil
from collections.abc import Callable, Sequence
from functools import lru_cache
from pathlib import Path

import numpy as np

from hgca_core.errors import InputError
from hgca_core.geometry.freespace import dense
from hgca_core.io.atomic import atomic_write

MARK = "packed_coarse"   # key present in every packed file; its value is the format version
VERSION = 1
SPLITS = ("train", "val", "test")


@lru_cache(maxsize=4096)
def _packed(path: str) -> bool:
    try:
        with np.load(path, allow_pickle=False) as z:
            return MARK in z.files
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read the sample: {e}", path) from None


def is_packed(path: str | Path) -> bool:
    """Whether a sample file is a packed coarse sample (looked up once per path)."""
    return _packed(str(path))


def refuse_packed(files: Sequence[str | Path], what: str) -> None:
    """A clear error where a consumer needs the full samples (points, surfaces) but was given packed ones."""
    for f in {files[0], files[-1]} if files else ():
        if is_packed(f):
            raise InputError(f"{what} needs the full samples (`hgca synth --split`); this is a packed coarse sample "
                             "(`hgca synth --pack`), which holds only the coarse stage's 20 cm cells", f)


def _bits(cells: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    return np.packbits(dense(cells, shape).reshape(-1))


def unpack_cells(bits: np.ndarray, shape: Sequence[int]) -> np.ndarray:
    """(N, 3) int64 cells of a packed bit grid, in row-major (sorted) order."""
    n = int(np.prod(shape))
    return np.argwhere(np.unpackbits(bits, count=n).astype(bool).reshape(tuple(int(s) for s in shape))).astype(np.int64)


def pack_sample(src: str | Path, dst: str | Path, visible: bool) -> Path:
    """Write the packed coarse sample of the full sample `src` to `dst` (atomically); with `visible`, also the
    visible cells that validation scores. The cells are those `training.data` computes from `src`."""
    from hgca_core.training.data import coarse_pair, free_cells, load_arrays

    s0, gt, shape = coarse_pair(src)
    arrays = {MARK: np.int64(VERSION), "region": load_arrays(str(src), ("region",))["region"],
              "grid": np.asarray(shape, dtype=np.int64), "s0": _bits(s0, shape), "gt": _bits(gt, shape),
              "free": _bits(free_cells(src), shape)}
    if visible:
        arrays["visible20"] = _bits(load_arrays(str(src), ("visible20",))["visible20"], shape)
    return Path(atomic_write(dst, lambda f: np.savez_compressed(f, **arrays)))


def pack_dataset(src: str | Path, out: str | Path, splits: Sequence[str] = SPLITS,
                 progress: Callable[[int, int], None] | None = None) -> list[Path]:
    """Pack every sample of `src`'s splits into `out`/<split>/ (same names); a packed file newer than its source
    is kept, so an interrupted or growing dataset packs again from where it stopped. The recipe goes along."""
    src, out = Path(src), Path(out)
    if src.resolve() == out.resolve():
        raise InputError("--pack writes beside its source, not over it: give another --out folder", out)
    jobs = [(f, out / split / f.name, split != "train") for split in splits
            for f in sorted((src / split).glob("sample_*.npz"))]
    if not jobs:
        raise InputError(f"no samples in {', '.join(str(src / s) for s in splits)}", src)
    done = []
    for k, (f, target, visible) in enumerate(jobs):
        if is_packed(f):
            raise InputError("already a packed sample: pack the full dataset it came from", f)
        if not (target.exists() and target.stat().st_mtime_ns >= f.stat().st_mtime_ns):
            target.parent.mkdir(parents=True, exist_ok=True)
            pack_sample(f, target, visible)
        done.append(target)
        if progress is not None:
            progress(k + 1, len(jobs))
    recipe = src / "recipe.json"
    if recipe.exists():
        shutil.copyfile(recipe, out / "recipe.json")
    (out / "packed.json").write_text(json.dumps({"packed_from": str(src), "format": VERSION,
                                                 "samples": {s: sum(1 for d in done if d.parent.name == s)
                                                             for s in splits}}, indent=1) + "\n")
    return done

"""Writing packed coarse samples (`hgca synth --pack`): each from its full sample, through the very functions
the coarse stage reads full samples with, so a packed file gives the cells its source gives."""
from __future__ import annotations

import json
import shutil
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from hgca_core.dataset.packed import MARK, SPLITS, VERSION, is_packed, pack_bits
from hgca_core.dataset.samples import load_arrays
from hgca_core.errors import InputError
from hgca_core.io.atomic import atomic_write
from hgca_core.training.data import coarse_pair, free_cells


def pack_sample(src: str | Path, dst: str | Path, visible: bool) -> Path:
    """Write the packed coarse sample of the full sample `src` to `dst` (atomically); with `visible`, also the
    visible cells that validation scores. The cells are those `training.data` computes from `src`."""
    s0, gt, shape = coarse_pair(src)
    arrays = {MARK: np.int64(VERSION), "region": load_arrays(str(src), ("region",))["region"],
              "grid": np.asarray(shape, dtype=np.int64), "s0": pack_bits(s0, shape), "gt": pack_bits(gt, shape),
              "free": pack_bits(free_cells(src), shape)}
    if visible:
        arrays["visible20"] = pack_bits(load_arrays(str(src), ("visible20",))["visible20"], shape)
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

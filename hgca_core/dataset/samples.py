"""The synthetic sample file (CONTRACTS.md): one compressed .npz per sample, in `<split>/sample_{seed:07d}.npz`.

Why here: the simulator (`synth.dataset`) writes these files, and training, `hgca eval` and the benchmarks read
them; keeping the format apart lets a reader open a sample without importing the simulator.
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.atomic import atomic_write

SPLITS = {"train": 0, "val": 1_000_000, "test": 2_000_000}
SPLIT_SPAN = 1_000_000   # seeds a split may use before the next split's
FORMAT_VERSION = 3      # layout of the sample file (CONTRACTS.md); 2 added ground_height, 3 the hits beyond the region
KEYS = ("region", "input_points", "input_scan_index", "input_far_points", "input_far_scan_index", "input_origins",
        "input_poses", "gt_occ20", "gt_occ10",
        "gt_surface", "gt_surface_label", "udf_points", "udf_dist", "eval_poses", "eval_scan_0", "eval_scan_1",
        "visible20", "street_box", "ground_z", "ground_height", "meta")


def sample_path(out_dir: str | os.PathLike, split: str, seed: int) -> Path:
    return Path(out_dir, split, f"sample_{seed:07d}.npz")


def save_sample(path: str | os.PathLike, sample: dict) -> str:
    """Write a compressed .npz atomically (temp file in the same folder, then os.replace)."""
    missing = [k for k in KEYS if k not in sample]
    if missing:
        raise ValueError(f"sample lacks {', '.join(missing)}")
    # (N, 3) arrays go column-major: runs of equal coordinates compress up to 50x better
    arrays = {k: np.asfortranarray(sample[k]) if np.ndim(sample[k]) == 2 else sample[k] for k in KEYS}
    return atomic_write(path, lambda f: np.savez_compressed(f, **arrays))


def load_sample(path: str | os.PathLike) -> dict:
    """All arrays of a sample file, as np.load gives them (`json.loads(str(s["meta"]))` for the meta dict)."""
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def split_files(data: str | Path | Sequence[str | Path], split: str) -> list[Path]:
    """Sample files of a split, sorted, so that an index names the same sample on every run.

    `data` may name several dataset folders (newer scenes built beside a dataset with `hgca synth --first`):
    the train split is then the union of theirs, in the order given, and any other split is the first
    folder's, so that validation compares like with like across runs that add data. The first of several folders
    may hold only a val split (the validation scenes alone, packed apart from the training batches)."""
    folders = [data] if isinstance(data, (str, Path)) else list(data)
    out = []
    for i, folder in enumerate(folders if split == "train" else folders[:1]):
        files = sorted(Path(folder, split).glob("sample_*.npz"))
        if not files and not (split == "train" and i == 0 and len(folders) > 1
                              and any(Path(folder, "val").glob("sample_*.npz"))):
            raise InputError(f"no samples in {Path(folder, split)}; make them with `hgca synth --split {split}`")
        out += files
    return out


@lru_cache(maxsize=64)
def load_arrays(path: str, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Load only the named arrays of a sample (npz members load lazily), cached across chain resets."""
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in keys}

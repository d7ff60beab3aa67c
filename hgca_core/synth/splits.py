"""Dataset splits of synthetic samples: built in parallel, resumable, one builder a split, and a recipe.json that
records what made them (generator and format versions, quality, each seed's sensor profile and scan count), so a
folder never mixes samples of different kinds."""
from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path

from hgca_core.dataset.samples import FORMAT_VERSION, SPLIT_SPAN, SPLITS, load_sample, sample_path, save_sample
from hgca_core.synth.dataset import DEFAULT_QUALITY, SCANS, Quality, draw_recipe, make_sample
from hgca_core.synth.lidar import PROFILES
from hgca_core.synth.scene import GENERATOR_VERSION, STYLE_DRAWS


def _build_one(job: tuple[str, str, int, int | None, Quality, int]) -> tuple[int, float]:
    out_dir, split, seed, n_scans, quality, generator = job
    t = time.perf_counter()
    save_sample(sample_path(out_dir, split, seed), make_sample(seed, n_scans, quality=quality, generator=generator))
    return seed, time.perf_counter() - t


_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")
RECIPE = "recipe.json"


def _single_thread() -> None:
    for var in _THREAD_VARS:
        os.environ[var] = "1"


def quality_record(quality: Quality) -> dict:
    """The numbers that decide a sample's content (so a resumed build can check it makes the same kind)."""
    return {"azimuth_fraction": quality.azimuth_fraction, "effects": dataclasses.asdict(quality.effects),
            "eval_beams": len(quality.eval_sensor.elevations_deg), "eval_azimuth": quality.eval_sensor.n_azimuth,
            "visibility_azimuth": quality.visibility_azimuth, "surface_density": quality.surface_density,
            "gt_surface_points": quality.gt_surface_points, "udf_points": quality.udf_points,
            "scan_radius": quality.scan_radius, "quantum": quality.quantum}


def update_recipe(out_dir: str | os.PathLike, split: str, seeds: list[int], n_scans: int | None,
                  quality: Quality, generator: int | None = None) -> dict:
    """Read, check and extend out_dir/recipe.json: generator and format versions, the quality, and per split
    each seed's sensor profile and scan count. A folder made by another generator version or quality is
    refused (mixing them would make a split whose samples differ in kind). `generator` None: the folder's own
    version (a build resumed or extended goes on as it began), the latest for a new folder."""
    from hgca_core.errors import InputError
    from hgca_core.io.atomic import atomic_write

    path = Path(out_dir, RECIPE)
    recipe = None
    if path.exists():
        try:
            recipe = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise InputError(f"cannot read the dataset recipe ({exc})", str(path)) from None
        if generator is None:
            generator = recipe.get("generator_version")
            if generator not in STYLE_DRAWS:
                raise InputError(f"this folder was built by generator version {generator!r}, which this version "
                                 f"cannot make (it makes {', '.join(map(str, STYLE_DRAWS))}); build into a new "
                                 "folder", str(path))
    generator = GENERATOR_VERSION if generator is None else generator
    if generator not in STYLE_DRAWS:
        raise InputError(f"unknown generator version {generator!r}; use one of {', '.join(map(str, STYLE_DRAWS))}")
    want = {"generator_version": generator, "format_version": FORMAT_VERSION, "quality": quality_record(quality)}
    if recipe is not None:
        for key, val in want.items():
            if json.loads(json.dumps(val)) != recipe.get(key):
                raise InputError(f"this folder was built with another {key.replace('_', ' ')} ({recipe.get(key)!r}, "
                                 f"now {val!r}); build into a new folder", str(path))
    else:
        old = sorted(Path(out_dir).glob("*/sample_*.npz"))
        if old:
            meta = json.loads(str(load_sample(old[0])["meta"]))
            raise InputError(f"this folder holds samples without a recipe (generator version "
                             f"{meta.get('generator_version')}); build into a new folder", str(out_dir))
        recipe = {**want, "profiles": sorted(PROFILES), "scans": list(SCANS), "split_seed_start": SPLITS, "splits": {}}
    table = recipe["splits"].setdefault(split, {})
    for seed in seeds:
        if str(seed) in table and sample_path(out_dir, split, seed).exists():
            continue                                   # made already: keep what it was made with
        prof, drawn = draw_recipe(seed)
        table[str(seed)] = {"profile": prof, "n_scans": drawn if n_scans is None else int(n_scans)}
    recipe["splits"][split] = dict(sorted(table.items(), key=lambda kv: int(kv[0])))
    payload = (json.dumps(recipe, indent=1) + "\n").encode()
    atomic_write(path, lambda f: f.write(payload))
    return recipe


class _SplitLock:
    """out_dir/<split>/.lock holding the builder's pid: two builders never write one split; a lock left by
    a killed builder is taken over (with the temp files it left)."""

    def __init__(self, folder: Path) -> None:
        self.path = folder / ".lock"

    def __enter__(self) -> "_SplitLock":
        from hgca_core.errors import InputError

        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            except FileExistsError:
                try:
                    pid = int(self.path.read_text().strip() or 0)
                    os.kill(pid, 0)
                except (ValueError, ProcessLookupError, OSError):
                    self.path.unlink(missing_ok=True)           # stale: its builder is gone
                    for tmp in self.path.parent.glob(".sample_*.tmp"):
                        tmp.unlink(missing_ok=True)
                    continue
                raise InputError(f"another build (pid {pid}) is writing this split", str(self.path.parent)) from None
            with os.fdopen(fd, "w") as f:
                f.write(str(os.getpid()))
            return self
        raise InputError("cannot take the split's lock", str(self.path))

    def __exit__(self, *exc) -> None:
        self.path.unlink(missing_ok=True)


def build_split(out_dir: str | os.PathLike, split: str, count: int, n_scans: int | None = None, workers: int = 2,
                progress: bool = True, quality: Quality = DEFAULT_QUALITY, first: int = 0,
                generator: int | None = None) -> list[Path]:
    """Write out_dir/<split>/sample_<seed>.npz for `count` of the split's seeds from its `first`-th, in `workers`
    processes.

    Incremental and resumable: finished files are skipped (writes are atomic, so a file that exists is
    complete), and out_dir/recipe.json records the generator version, the quality and each seed's sensor
    profile and scan count (drawn from the seed unless `n_scans` fixes it). `generator`: the scene generator
    version (None: the folder's own, or the latest for a new folder; 6 rebuilds synth2 as it was made).
    """
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; use one of {', '.join(SPLITS)}")
    if first < 0 or first + count > SPLIT_SPAN:
        from hgca_core.errors import InputError

        raise InputError(f"--first {first} with --count {count}: seeds {first}..{first + count - 1} of a split must "
                         f"lie in 0..{SPLIT_SPAN - 1} (the next split's start after)")
    seeds = [SPLITS[split] + first + i for i in range(count)]
    Path(out_dir, split).mkdir(parents=True, exist_ok=True)
    from tqdm import tqdm

    with _SplitLock(Path(out_dir, split)):
        generator = update_recipe(out_dir, split, seeds, n_scans, quality, generator)["generator_version"]
        todo = [s for s in seeds if not sample_path(out_dir, split, s).exists()]
        jobs = [(os.fspath(out_dir), split, s, n_scans, quality, generator) for s in todo]
        bar = tqdm(total=len(seeds), initial=len(seeds) - len(todo), desc=f"synth {split}", unit="sample",
                   disable=not progress)
        try:
            if workers <= 1 or len(jobs) <= 1:
                for job in jobs:
                    _build_one(job)
                    bar.update(1)
            else:
                import multiprocessing as mp

                saved = {v: os.environ.get(v) for v in _THREAD_VARS}
                _single_thread()  # spawned children inherit this before they import numpy: one thread each
                try:
                    pool = mp.get_context("spawn").Pool(min(workers, len(jobs)), initializer=_single_thread)
                finally:
                    for var, val in saved.items():
                        if val is None:
                            os.environ.pop(var, None)
                        else:
                            os.environ[var] = val
                with pool:
                    for _ in pool.imap_unordered(_build_one, jobs):
                        bar.update(1)
        finally:
            bar.close()
    return [sample_path(out_dir, split, s) for s in seeds]

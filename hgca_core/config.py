"""The settings of a completion and of a drive, with their one set of defaults and limits.

`CompletionConfig` is what `hgca complete`, `hgca demo`, `hgca eval`, `hgca bench`, the Python API
(`hgca_core.complete`) and the Blender add-on's job complete with; `DriveConfig` adds what `hgca drive` /
`hgca_core.drive` tiles with. Commands map argv to a config and call the library, so a default or a bound is
written here once. Every field is checked when the config is made (`InputError` naming the field and the value);
whether a CUDA device exists is the one thing only known at run time (`pipeline.check_device`).

Torch- and numpy-free: argument parsing imports this module, and the add-on's limits are read from it
(`addon_limits`, checked against hgca_blender/properties.py by tests/test_config_addon.py).
"""
from __future__ import annotations

import math
import numbers
import re
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from hgca_core.errors import InputError
from hgca_core.nn.precision import DEFAULT_PRECISION, PRECISIONS

STAGES = ("preview", "coarse", "full")
# Quality levels: which shipped weights a completion runs when no weights file is named. best = the teacher chains
# (T1 30, T2 15: coarse.pt, fine.pt); fast = the few-step students trained from them (T1 10, T2 5:
# coarse_student.pt, fine_student.pt; `hgca train --recipe coarse-student / fine-student`). Their measured
# quality and speed side by side: MODEL_CARD.md.
QUALITIES = ("fast", "best")
DEFAULT_QUALITY = "best"
QUALITY_FILES = {"best": ("coarse.pt", "fine.pt"), "fast": ("coarse_student.pt", "fine_student.pt")}
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
# Observed free space: feature = the networks' input; mask = also forbid its core; auto = mask for weights trained
# with the feature, nothing for others; off = neither (`pipeline.observed_free`).
FREE_SPACE_MODES = ("auto", "feature", "mask", "off")
MESH_FORMATS = ("ply", "glb", "obj", "npz")
# Sample i of a run uses seed + i; torch's generators take at most 2**64 - 1, so every seed stays within int64.
SEED_MAX = 2**63 - 1
MAX_SAMPLES = 1000
MAX_STEPS = 1000          # a step is a pass of the network: 10^9 steps would never end
MIN_FACES = 1000          # a face limit below this is no mesh of a street
DEFAULT_MAX_FACES = 1_000_000   # a default region's full-stage mesh has ~2 M triangles
MIN_STRIDE = 0.2          # metres between tile centres: one coarse cell (a finer stride only repeats tiles)
MAX_WORKERS = 4096
MAX_THREADS = 4096
TILE_SIZE = 38.4          # metres: the paper's region
TILE_OVERLAP = 6.4        # metres: 32 coarse cells, wider than the GCA's receptive field on either side
_DEVICE = re.compile(r"cpu|cuda(:\d+)?")


def _whole(name: str, value: Any, low: int, high: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low or (
            high is not None and value > high):
        top = "2**63 - 1" if high == SEED_MAX else high
        span = f"at least {low}" if high is None else f"between {low} and {top}"
        raise InputError(f"{name} must be a whole number {span}, got {value!r}")
    return int(value)


def _choice(name: str, value: Any, choices: tuple[str, ...]) -> str:
    if value not in choices:
        raise InputError(f"{name} must be one of {', '.join(choices)}, not {value!r}")
    return value


def _finite(name: str, value: Any, low: float = 0.0, strict: bool = True) -> float:
    bad = isinstance(value, bool) or not isinstance(value, numbers.Real)
    if bad or not math.isfinite(value) or (value <= low if strict else value < low):
        raise InputError(f"{name} must be a finite number {'above' if strict else 'of at least'} {low:g}, "
                         f"got {value!r}")
    return float(value)


def check_device_name(device: Any) -> str:
    """cpu, cuda or cuda:N (whether that GPU exists is `pipeline.check_device`'s, at run time)."""
    if not isinstance(device, str) or not _DEVICE.fullmatch(device):
        raise InputError(f"unknown device {device!r}: use cpu, cuda or cuda:N")
    return device


@dataclass(frozen=True)
class CompletionConfig:
    """How one region is completed (`hgca complete`'s options).

    stage: "full" = 20 cm coarse GCA, 10 cm cGCA upsampling and an implicit mesh; "coarse" = the 20 cm cells'
        blocky mesh only (faster); "preview" = the coarse cells as a smooth surface (scikit-image's marching
        cubes of their blurred occupancy), for deciding where a region goes.
    quality: the shipped weights used when `weights` / `fine_weights` are None (QUALITIES): fast = the few-step
        students, best = the paper's 30 + 15 step chains.
    samples: completions k, one mesh each; sample i uses seed + i, so a (seed, i) pair names one mesh.
    t1, t2: coarse / fine steps; None or 0 = the weights' own (30 and 15 for the shipped ones).
    weights, fine_weights: weights files; None = the shipped ones.
    device: cpu, cuda or cuda:N.
    precision: GEMM precision of the sparse convs (fp32: the same mesh on any thread count).
    max_faces: simplify each mesh to at most this many triangles; 0 keeps every one (None: the default).
    free_space: what observed free space does (FREE_SPACE_MODES).
    semantics: label every face with a class (`hgca_core.models.semantics`); semantics_weights: its weights file
        (None = the shipped semantics.pt). The geometry is the same with or without it.
    """

    stage: str = "full"
    samples: int = 1
    seed: int = 0
    t1: int | None = None
    t2: int | None = None
    weights: str | None = None
    fine_weights: str | None = None
    device: str = "cpu"
    precision: str = DEFAULT_PRECISION
    max_faces: int = DEFAULT_MAX_FACES
    free_space: str = "auto"
    semantics: bool = False
    semantics_weights: str | None = None
    quality: str = DEFAULT_QUALITY

    def __post_init__(self) -> None:
        if self.max_faces is None:
            object.__setattr__(self, "max_faces", DEFAULT_MAX_FACES)
        _choice("stage", self.stage, STAGES)
        _choice("quality", self.quality, QUALITIES)
        _whole("samples", self.samples, 1, MAX_SAMPLES)
        _whole("seed", self.seed, 0, SEED_MAX)
        check_seed_span(self.seed, self.samples)
        for name in ("t1", "t2"):
            steps = getattr(self, name)
            if steps is not None and (isinstance(steps, bool) or not isinstance(steps, numbers.Integral)
                                      or not 0 <= steps <= MAX_STEPS):
                raise InputError(f"{name} must be a whole number >= 0 and at most {MAX_STEPS} (0: the weights' "
                                 f"own), got {steps!r}")
        max_faces = _whole("max_faces", self.max_faces, 0)
        if max_faces and max_faces < MIN_FACES:
            raise InputError(f"max_faces must be 0 (keep every triangle) or at least {MIN_FACES}, got {max_faces}")
        for name in ("weights", "fine_weights", "semantics_weights"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, str(value))     # a Path is kept as its text: configs compare equal
        check_device_name(self.device)
        _choice("precision", self.precision, PRECISIONS)
        _choice("free_space", self.free_space, FREE_SPACE_MODES)

    def coarse_file(self) -> str | None:
        """The coarse weights to load: `weights`, else the quality's shipped file (None: the loader's default,
        the teacher's coarse.pt)."""
        return self.weights or self._shipped(0)

    def fine_file(self) -> str | None:
        """The fine weights to load (the full stage): `fine_weights`, else the quality's shipped file."""
        return self.fine_weights or self._shipped(1)

    def _shipped(self, stage: int) -> str | None:
        """The quality's shipped file of stage 0 (coarse) or 1 (fine); None for best, the loaders' own default."""
        return None if self.quality == "best" else str(WEIGHTS_DIR / QUALITY_FILES[self.quality][stage])

    def with_(self, **changes: Any) -> "CompletionConfig":
        """A copy with `changes` (field names), checked again; an unknown name is an `InputError`."""
        unknown = sorted(set(changes) - {f.name for f in fields(self)})
        if unknown:
            raise InputError(f"unknown completion setting(s) {', '.join(unknown)}; the settings are "
                             f"{', '.join(f.name for f in fields(self))}")
        return replace(self, **changes)


def check_seed_span(seed: int, count: int, what: str = "samples") -> None:
    """Refuse a seed whose last use (seed + count - 1) leaves the 64-bit range, before the first sample runs."""
    if seed + max(count, 1) - 1 > SEED_MAX:
        raise InputError(f"seed {seed} with {count} {what} would use seeds up to {seed + count - 1}, past "
                         f"2**63 - 1; choose a seed of at most {SEED_MAX - count + 1}")


def _tile_completion() -> CompletionConfig:
    return CompletionConfig(max_faces=0)


@dataclass(frozen=True)
class DriveConfig:
    """How a drive is tiled and each tile completed (`hgca drive`'s options).

    completion: each tile's completion; sample k of tile i uses seed + i * samples + k. Its default keeps every
        triangle of a tile (max_faces 0), so neighbouring tiles' surfaces meet at the seams as computed.
    size, overlap: tile side and overlap of consecutive tiles, metres (tiles are 8 m high).
    scans_per_tile: each tile is completed from its N nearest scans (N above the drive's scan count: all of them).
    seams: condition each second-phase tile on its finished neighbours' coarse cells (joins agree).
    workers: tiles at once; more than 1 (or an `address`) runs them on Ray.
    address: an existing Ray cluster (ray://host:port), or None.
    threads: torch threads per tile; None = cores / workers.
    tile_memory: bytes each tile declares to Ray; None = estimated from the tile's area.
    mesh_format: the tile and drive meshes' format (MESH_FORMATS).
    """

    completion: CompletionConfig = field(default_factory=_tile_completion)
    size: float = TILE_SIZE
    overlap: float = TILE_OVERLAP
    scans_per_tile: int = 5
    seams: bool = True
    workers: int = 1
    address: str | None = None
    threads: int | None = None
    tile_memory: float | None = None
    mesh_format: str = "ply"

    def __post_init__(self) -> None:
        if not isinstance(self.completion, CompletionConfig):
            raise InputError(f"completion must be a CompletionConfig, got {type(self.completion).__name__}")
        check_stride(self.size, self.overlap)
        _whole("scans_per_tile", self.scans_per_tile, 1)   # more than the drive's scans: all of them
        if not isinstance(self.seams, bool):
            raise InputError(f"seams must be True or False, got {self.seams!r}")
        _whole("workers", self.workers, 1, MAX_WORKERS)
        if self.threads is not None:
            _whole("threads", self.threads, 1, MAX_THREADS)
        if self.tile_memory is not None:
            _finite("tile_memory", self.tile_memory)
        if self.address is not None and not isinstance(self.address, str):
            raise InputError(f"address must be a Ray address (ray://host:port), got {self.address!r}")
        _choice("mesh_format", self.mesh_format, MESH_FORMATS)

    def with_(self, **changes: Any) -> "DriveConfig":
        """A copy with `changes`: drive fields by name, completion fields (stage, seed, ...) into `completion`."""
        own = {f.name for f in fields(self)}
        tile = {k: v for k, v in changes.items() if k not in own}
        if "max_faces" in tile and tile["max_faces"] is None:      # None: the default, a tile's own
            tile["max_faces"] = _tile_completion().max_faces
        drive = {k: v for k, v in changes.items() if k in own}
        completion = drive.pop("completion", self.completion)
        return replace(self, completion=completion.with_(**tile) if tile else completion, **drive)


def check_stride(size: float, overlap: float) -> float:
    """The stride `size - overlap` between tiles, or an `InputError` naming the flags: a stride of micrometres
    (--overlap 12.79999 --size 12.8) would plan millions of identical tiles."""
    if isinstance(size, bool) or not isinstance(size, numbers.Real) or not (math.isfinite(size) and size > 0):
        raise InputError(f"--size must be a finite tile side above 0 m, got {size}")
    bad = isinstance(overlap, bool) or not isinstance(overlap, numbers.Real)
    if bad or not (math.isfinite(overlap) and 0 < overlap < size):
        raise InputError(f"--overlap must be between 0 and the tile size (--size {size} m), got {overlap}")
    stride = size - float(overlap)
    if stride < MIN_STRIDE - 1e-9:
        raise InputError(f"--size {size} with --overlap {overlap} leaves {stride:.6g} m between tiles; the stride "
                         f"must be at least {MIN_STRIDE} m (one coarse cell): lower --overlap")
    return stride


def addon_limits() -> dict[str, dict[str, Any]]:
    """Each setting the Blender add-on shows: its default and the core's bounds (None: unbounded). The add-on
    cannot import the core (it runs it as a subprocess), so a test holds its properties to these."""
    c, d = CompletionConfig(), DriveConfig()
    return {
        "samples": {"default": c.samples, "min": 1, "max": MAX_SAMPLES},
        "seed": {"default": c.seed, "min": 0, "max": SEED_MAX},
        "stage": {"default": c.stage, "choices": list(STAGES)},
        "quality": {"default": c.quality, "choices": list(QUALITIES)},
        "device": {"default": c.device},
        "t1": {"default": c.t1 or 0, "min": 0, "max": MAX_STEPS},
        "t2": {"default": c.t2 or 0, "min": 0, "max": MAX_STEPS},
        "max_faces": {"default": c.max_faces, "min": MIN_FACES, "max": None},
        "drive_tile_size": {"default": d.size, "min": MIN_STRIDE, "max": None},
        "drive_overlap": {"default": d.overlap, "min": 0.0, "max": None},
        "drive_workers": {"default": d.workers, "min": 1, "max": MAX_WORKERS},
    }


# The CLI flag of each setting the add-on shows (`hgca complete` / `hgca drive`), for its one config -> argv
CLI_FLAGS = {"samples": "--samples", "seed": "--seed", "stage": "--stage", "quality": "--quality",
             "device": "--device", "t1": "--t1", "t2": "--t2", "max_faces": "--max-faces",
             "drive_tile_size": "--size", "drive_overlap": "--overlap", "drive_workers": "--workers"}


def addon_schema() -> dict[str, Any]:
    """What the Blender add-on knows of the core's settings, as JSON: each setting's default, bounds and choices
    (`addon_limits`) and its CLI flag. The extension build writes it into the zip (`core_settings.json`), and the
    add-on makes its panel properties and every job's command line from it, so the two cannot drift apart."""
    return {"schema": 1, "settings": addon_limits(), "flags": dict(CLI_FLAGS)}


def as_dict(config: CompletionConfig | DriveConfig) -> dict[str, Any]:
    """The config as plain JSON-able values (a run's record)."""
    return asdict(config)

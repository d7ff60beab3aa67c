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
from dataclasses import MISSING, Field, dataclass, field, fields, replace
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
REGION_SIZE = (38.4, 38.4, 8.0)   # metres: the paper's region (x, y along the ground, z up)
TILE_SIZE = REGION_SIZE[0]
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


# -- the settings' metadata: each field's kind, bounds, choices and help, read by the checks below, by the command
# line (`hgca_core.commands.arguments.add_config_arguments` makes each option from it) and by the add-on's schema

def setting(default: Any = MISSING, help: str = "", *, kind: str, low: float | None = None,
            high: float | None = None, choices: tuple[str, ...] = (), metavar: str | None = None,
            default_factory: Any = MISSING) -> Any:
    """A config field with its metadata. kind: choice, whole, steps (None or 0..MAX_STEPS, 0 = the weights' own),
    faces (0 or at least MIN_FACES), device, path (None or a file name), switch (a bool), number (a finite float
    above `low`), address (None or text), nested (a config of its own). Its command-line option is
    --name-with-dashes (`flag_of`)."""
    meta = {"kind": kind, "low": low, "high": high, "choices": choices, "help": help, "metavar": metavar}
    if default_factory is not MISSING:
        return field(default_factory=default_factory, metadata=meta)
    return field(default=default, metadata=meta)


def check_setting(f: Field, value: Any) -> Any:
    """`value` checked against field `f`'s metadata (an `InputError` naming the field and the value), normalised
    (a whole number as int, a Path as its text). The one place a setting's bound is checked: the config's
    constructor calls it for every field, and the command line's option types call it while parsing."""
    m, name = f.metadata, f.name
    kind = m["kind"]
    if kind == "choice":
        return _choice(name, value, m["choices"])
    if kind == "whole":
        return None if value is None and f.default is None else _whole(name, value, int(m["low"]),
                                                                       None if m["high"] is None else int(m["high"]))
    if kind == "steps":
        if value is not None and (isinstance(value, bool) or not isinstance(value, numbers.Integral)
                                  or not 0 <= value <= MAX_STEPS):
            raise InputError(f"{name} must be a whole number >= 0 and at most {MAX_STEPS} (0: the weights' own), "
                             f"got {value!r}")
        return None if value is None else int(value)
    if kind == "faces":
        value = DEFAULT_MAX_FACES if value is None else _whole(name, value, 0)
        if value and value < MIN_FACES:
            raise InputError(f"{name} must be 0 (keep every triangle) or at least {MIN_FACES}, got {value}")
        return value
    if kind == "device":
        return check_device_name(value)
    if kind == "path":
        if value is not None and not isinstance(value, (str, Path)):
            raise InputError(f"{name} must be a file name, got {value!r}")
        return None if value is None else str(value)     # a Path is kept as its text: configs compare equal
    if kind == "switch":
        if not isinstance(value, bool):
            raise InputError(f"{name} must be True or False, got {value!r}")
        return value
    if kind == "number":
        return None if value is None and f.default is None else _finite(name, value, m["low"] or 0.0)
    if kind == "address":
        if value is not None and not isinstance(value, str):
            raise InputError(f"{name} must be a Ray address (ray://host:port), got {value!r}")
        return value
    return value


def _check_fields(config: Any) -> None:
    for f in fields(config):
        if f.metadata.get("kind", "nested") != "nested":
            object.__setattr__(config, f.name, check_setting(f, getattr(config, f.name)))


@dataclass(frozen=True)
class CompletionConfig:
    """How one region is completed (`hgca complete`'s options; each field's help is its option's).

    Sample i of a run uses seed + i, so a (seed, i) pair names one mesh. `weights` / `fine_weights` None = the
    quality's shipped files; t1 / t2 None or 0 = the weights' own chain. The geometry is the same with or without
    `semantics`.
    """

    stage: str = setting("full", "full: 20 cm coarse GCA, 10 cm cGCA upsampling and an implicit mesh; coarse: the "
                         "20 cm voxels only (faster); preview: the coarse cells as a smooth surface (scikit-image's "
                         "marching cubes), for deciding where a region goes (fastest)", kind="choice", choices=STAGES)
    samples: int = setting(1, "number of completions k, one mesh each", kind="whole", low=1, high=MAX_SAMPLES)
    seed: int = setting(0, "sample i uses seed + i: same seed, same mesh", kind="whole", low=0, high=SEED_MAX,
                        metavar="N")
    t1: int | None = setting(None, "coarse steps T1 (0 or left out: the weights' own, 30 for coarse.pt, 10 for the "
                             "fast quality's student)", kind="steps")
    t2: int | None = setting(None, "fine steps T2 (0 or left out: the weights' own, 15 for fine.pt, 5 for the fast "
                             "quality's student)", kind="steps")
    weights: str | None = setting(None, "coarse weights file or training checkpoint (default: the quality's "
                                  "shipped file)", kind="path")
    fine_weights: str | None = setting(None, "fine weights file, stage full (default: the quality's shipped file)",
                                       kind="path")
    device: str = setting("cpu", "cpu, cuda or cuda:N", kind="device")
    precision: str = setting(DEFAULT_PRECISION, "GEMM precision of the sparse convs while sampling (fp32: the same "
                             "mesh on any thread count; bf16 is faster where the CPU has AVX512-BF16/AMX but its "
                             "mesh may differ between thread counts; auto: bf16 where the hardware has it)",
                             kind="choice", choices=PRECISIONS)
    max_faces: int = setting(DEFAULT_MAX_FACES, "simplify each mesh to at most this many triangles (0 keeps every "
                             "triangle: a default region's full-stage mesh has 1.9-3.1 M)", kind="faces")
    free_space: str = setting("auto", "observed free space: what the sensor saw through (needs sensor origins). "
                              "feature = give it to weights trained with it; mask = also never output a cell deep "
                              "in it (seen-empty cells whose six neighbours are seen empty); off = neither; auto = "
                              "mask where the weights take the feature (every shipped coarse and fine file does) "
                              "and the scans have sensor origins, nothing for weights without it",
                              kind="choice", choices=FREE_SPACE_MODES)
    semantics: bool = setting(False, "label every face with a class (road, sidewalk, building, car, tree, pole, "
                              "fence, shelter, person): a PLY face property `label`, NPZ `face_label`, one GLB "
                              "primitive per class; with --samples k also each face's class agreement across the "
                              "samples. The geometry is unchanged", kind="switch")
    semantics_weights: str | None = setting(None, "semantic head weights (default: the shipped semantics.pt); "
                                            "implies --semantics",
                                            kind="path")
    quality: str = setting(DEFAULT_QUALITY, "which shipped weights run when --weights / --fine-weights name none: "
                           "fast = the few-step students (T1 10, T2 5), best = the paper's chains (T1 30, T2 15); "
                           "their measured quality and speed: MODEL_CARD.md", kind="choice", choices=QUALITIES)

    def __post_init__(self) -> None:
        _check_fields(self)
        check_seed_span(self.seed, self.samples)

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
    """How a drive is tiled and each tile completed (`hgca drive`'s options; each field's help is its option's).

    completion: each tile's completion; sample k of tile i uses seed + i * samples + k. Its default keeps every
        triangle of a tile (max_faces 0), so neighbouring tiles' surfaces meet at the seams as computed.
    tile_memory is in bytes (the command line's --tile-memory in GiB).
    """

    completion: CompletionConfig = setting(kind="nested", default_factory=_tile_completion)
    size: float = setting(TILE_SIZE, "tile side in metres (the paper's region)", kind="number", low=MIN_STRIDE)
    overlap: float = setting(TILE_OVERLAP, "overlap of consecutive tiles in metres", kind="number", low=0.0)
    scans_per_tile: int = setting(5, "each tile is completed from its N nearest scans (N at or above the drive's "
                                  "scan count means all of them)", kind="whole", low=1, metavar="N")
    seams: bool = setting(True, "condition each second-phase tile on its finished neighbours' coarse cells (joins "
                          "agree)", kind="switch")
    workers: int = setting(1, "tiles at once; more than 1 starts a local Ray in this process (needs hgca[ray])",
                           kind="whole", low=1, high=MAX_WORKERS)
    address: str | None = setting(None, "run on an existing Ray cluster (ray://host:port)", kind="address")
    threads: int | None = setting(None, "torch threads per tile (default: cores / workers)", kind="whole", low=1,
                                  high=MAX_THREADS, metavar="N")
    tile_memory: float | None = setting(None, "memory each tile declares to Ray (default: estimated from the "
                                        "tile's area)", kind="number", metavar="GIB")
    mesh_format: str = setting("ply", "tile and drive meshes", kind="choice", choices=MESH_FORMATS)

    def __post_init__(self) -> None:
        if not isinstance(self.completion, CompletionConfig):
            raise InputError(f"completion must be a CompletionConfig, got {type(self.completion).__name__}")
        check_stride(self.size, self.overlap)
        _check_fields(self)

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


# The settings the Blender add-on shows: its property name -> (config, field). Their defaults, bounds, choices and
# command-line flags are read off the fields' metadata, so the panel and the CLI cannot drift apart.
ADDON_SETTINGS = {**{name: (CompletionConfig, name) for name in ("samples", "seed", "stage", "quality", "device",
                                                                 "t1", "t2", "max_faces")},
                  "drive_tile_size": (DriveConfig, "size"), "drive_overlap": (DriveConfig, "overlap"),
                  "drive_workers": (DriveConfig, "workers")}
_BOUNDS = {"steps": (0, MAX_STEPS), "faces": (MIN_FACES, None)}   # the add-on's t1/t2 0 and faces > 0


def config_field(cls: type, name: str) -> Field:
    """The dataclass field `name` of config class `cls` (its metadata is the setting's description)."""
    return next(f for f in fields(cls) if f.name == name)


def flag_of(f: Field) -> str:
    """The command-line option of field `f`: --name-with-dashes."""
    return "--" + f.name.replace("_", "-")


def addon_limits() -> dict[str, dict[str, Any]]:
    """Each setting the Blender add-on shows: its default and the core's bounds (None: unbounded) or choices. The
    add-on cannot import the core (it runs it as a subprocess): the extension build ships these in the zip."""
    defaults = {CompletionConfig: CompletionConfig(), DriveConfig: DriveConfig()}
    out = {}
    for prop, (cls, name) in ADDON_SETTINGS.items():
        f, value = config_field(cls, name), getattr(defaults[cls], name)
        m = f.metadata
        entry: dict[str, Any] = {"default": 0 if value is None and m["kind"] == "steps" else value}
        if m["choices"]:
            entry["choices"] = list(m["choices"])
        elif m["kind"] != "device":
            low, high = _BOUNDS.get(m["kind"], (m["low"], m["high"]))
            entry.update(min=low if low is not None else 0.0, max=high)
        out[prop] = entry
    return out


# The CLI flag of each setting the add-on shows (`hgca complete` / `hgca drive`), for its one config -> argv
CLI_FLAGS = {prop: flag_of(config_field(cls, name)) for prop, (cls, name) in ADDON_SETTINGS.items()}


def addon_schema() -> dict[str, Any]:
    """What the Blender add-on knows of the core's settings, as JSON: each setting's default, bounds and choices
    (`addon_limits`), its CLI flag and its help. The extension build writes it into the zip (`core_settings.json`),
    and the add-on makes its panel properties and every job's command line from it, so the two cannot drift apart."""
    helps = {prop: config_field(cls, name).metadata["help"] for prop, (cls, name) in ADDON_SETTINGS.items()}
    return {"schema": 1, "settings": addon_limits(), "flags": dict(CLI_FLAGS), "help": helps,
            "region_size": list(REGION_SIZE)}

"""Training recipes as named configs in one table (`hgca train --recipe NAME --set key=value`).

Why one table: a recipe that lives in prose or in a shell string cannot be re-run exactly, and one that lives in
a dozen flags drifts between the run that made the weights and the next. Each entry is a frozen `Recipe`; a run
overrides fields with `--set` (typed and checked here, unknown keys refused), and the resolved recipe is saved in
the checkpoint, which `--resume` continues from.

The `*-shipped` entries are the recipes that made the shipped weights (their metadata records each run's
settings): every one continued the stage's then-shipped weights, so each starts from the shipped file of its
stage. `coarse-shipped` is the fine-tune behind `hgca_core/weights/coarse.pt`: cut, turned and focused crops with
the free space, the loss on seen-empty cells weighted 9x (also against what a cut input's uncut scan saw), cut
inputs distilled from the starting weights, batch 6, learning rate 1.5e-4, bf16 GEMMs; the export blends the run
back toward the weights it started from (0.7 start + 0.3 run, WiSE-FT). Nothing here imports torch.
"""
from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hgca_core.errors import InputError

STAGES = ("coarse", "coarse-noplanner", "autoencoder", "fine", "semantics")
WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights"


def shipped_file(stage: str) -> str:
    """The packaged weights of a stage (as `models.weights.shipped`, without importing torch)."""
    return str(WEIGHTS_DIR / f"{stage.replace('-', '_')}.pt")


@dataclass(frozen=True)
class Recipe:
    """Everything a training run is made of besides its data, budget, device and seed."""

    stage: str
    batch: int = 2                 # chains a step (per rank under torchrun)
    buffer: int = 8                # persistent chains kept (per rank)
    lr: float = 5e-4               # Adam's learning rate (the paper's)
    precision: str = "fp32"        # GEMM precision of the sparse convs in training (bf16: float32 accumulation)
    crop: int = 64                 # training crop in the stage's cells (coarse 20 cm, fine 10 cm)
    free_space: bool = False       # observed free space as a model input (coarse, fine)
    focus: float = 0.0             # coarse: share of crops drawn around missed cells 3 m or more up
    free_weight: float = 0.0       # coarse: the loss on seen-empty cells weighs 1 + free_weight
    cut: float = 0.0               # coarse: share of inputs cut 1.5-3 m above the ground
    cut_free_loss: bool = False    # coarse: on a cut input free_weight also falls where the uncut input saw empty
    turn: float = 0.0              # coarse: share of inputs turned by a random yaw about the sensor
    distill: float = 0.0           # coarse: on cut inputs the target moves this far to init_from's probability
    init_from: str | None = None   # weights or a checkpoint a new run starts from (and distils from)
    blend: float | None = None     # coarse export: (1 - blend) * init_from + blend * the run's weights
    channels: tuple[int, ...] | None = None   # coarse U-Net widths of a run started without init_from
    autoencoder: str | None = None  # fine: the frozen autoencoder (None: the shipped one)
    val_every: float = 10.0        # minutes between validation runs
    placement: str | None = None   # semantics: the head's input (geometry, coarse-features, fine-latents)
    steps: int | None = None       # coarse, fine: the chain's T (T1 / T2) the run trains and its weights sample
                                   # with (a few-step student); None keeps init_from's (or the model's default)
    alpha1: float | None = None    # coarse, fine: the infusion slope of that chain (alpha_t = alpha0 + alpha1 t)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @property
    def coarse(self) -> bool:
        return self.stage.startswith("coarse")


RECIPES: dict[str, Recipe] = {
    "coarse": Recipe(stage="coarse", focus=0.5),
    "coarse-noplanner": Recipe(stage="coarse-noplanner", focus=0.5),
    "autoencoder": Recipe(stage="autoencoder"),   # the shipped autoencoder.pt's recipe too
    "fine": Recipe(stage="fine"),
    "coarse-shipped": Recipe(stage="coarse", batch=6, lr=1.5e-4, precision="bf16", free_space=True, focus=0.5,
                             free_weight=8.0, cut=0.5, cut_free_loss=True, turn=0.5, distill=1.0,
                             init_from=shipped_file("coarse"), blend=0.3),
    "coarse-noplanner-shipped": Recipe(stage="coarse-noplanner", precision="bf16", free_space=True, focus=0.5,
                                       init_from=shipped_file("coarse-noplanner")),
    "fine-shipped": Recipe(stage="fine", precision="bf16", free_space=True, init_from=shipped_file("fine")),
    # few-step students (hgca complete --quality fast): the shipped weights trained on for chains of T1 = 10 and
    # T2 = 5 steps, infusion training on the short schedule (alpha_t ends where the teacher's 30- and 15-step
    # chains end, 0.295 and 0.22), with the teacher's other settings
    "coarse-student": Recipe(stage="coarse", batch=4, buffer=12, lr=1.5e-4, free_space=True, focus=0.5,
                             free_weight=8.0, cut=0.5, cut_free_loss=True, turn=0.5,
                             init_from=shipped_file("coarse"), steps=10, alpha1=0.0161, val_every=12.0),
    "fine-student": Recipe(stage="fine", lr=1.5e-4, free_space=True, init_from=shipped_file("fine"), steps=5,
                           alpha1=0.0175, val_every=12.0),
    # the semantic head (hgca_core.models.semantics): a one-step task on perturbed ground-truth cells, 80-cell crops
    "semantics": Recipe(stage="semantics", batch=2, buffer=2, lr=1e-3, crop=80, val_every=8.0),
    # the same head on the frozen coarse kernel's last decoder features, and on the fine stage's pooled latents
    "semantics-coarse-features": Recipe(stage="semantics", batch=2, buffer=2, lr=1e-3, crop=80, val_every=8.0,
                                        placement="coarse-features"),
    "semantics-fine-latents": Recipe(stage="semantics", batch=2, buffer=2, lr=1e-3, crop=80, val_every=8.0,
                                     placement="fine-latents"),
}
DEFAULT = "coarse"

# fields a resumed run may change from its saved recipe (the rest fix the model or where the run started)
RESUMABLE = frozenset({"batch", "buffer", "lr", "precision", "crop", "focus", "free_weight", "cut", "cut_free_loss",
                       "turn", "distill", "blend", "val_every"})
COARSE_ONLY = ("focus", "free_weight", "cut", "cut_free_loss", "turn", "distill", "blend", "channels")
MAX_COUNT = 1 << 16
SEMANTIC_PLACEMENTS = ("geometry", "coarse-features", "fine-latents")   # models.semantics.PLACEMENTS


def _field_types() -> dict[str, Any]:
    hints = typing.get_type_hints(Recipe)
    return {f.name: hints[f.name] for f in dataclasses.fields(Recipe)}


def _parse(key: str, kind: Any, text: str) -> Any:
    """`text` as a value of the field's type: whole numbers, finite numbers, true/false, comma lists, none."""
    args = typing.get_args(kind)
    optional = type(None) in args and (typing.get_origin(kind) in (typing.Union, types.UnionType))
    if optional:
        if text.strip().lower() in ("none", ""):
            return None
        kind = next(a for a in args if a is not type(None))
    if kind is bool:
        low = text.strip().lower()
        if low not in ("true", "false", "1", "0", "yes", "no"):
            raise InputError(f"--set {key}: expected true or false, got {text!r}")
        return low in ("true", "1", "yes")
    if kind is int:
        try:
            return int(text)
        except ValueError:
            raise InputError(f"--set {key}: not a whole number: {text!r}") from None
    if kind is float:
        try:
            value = float(text)
        except ValueError:
            raise InputError(f"--set {key}: not a number: {text!r}") from None
        if not math.isfinite(value):
            raise InputError(f"--set {key}: must be a finite number, got {text!r}")
        return value
    if typing.get_origin(kind) is tuple:
        try:
            return tuple(int(v) for v in text.split(","))
        except ValueError:
            raise InputError(f"--set {key}: expected comma-separated whole numbers, got {text!r}") from None
    return text


def parse_sets(items: list[str]) -> dict[str, Any]:
    """`--set key=value` items as typed fields of `Recipe`; an unknown key or a bad value is an `InputError`."""
    types_ = _field_types()
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise InputError(f"--set expects key=value, got {item!r}")
        if key == "stage":
            raise InputError("--set stage: the recipe names the stage; choose another --recipe")
        if key not in types_:
            raise InputError(f"--set {key}: no such recipe field; fields: {', '.join(k for k in types_ if k != 'stage')}")
        if key in out:
            raise InputError(f"--set {key} given twice")
        out[key] = _parse(key, types_[key], text)
    return out


def _between(name: str, value: float, low: float, high: float) -> None:
    if not (math.isfinite(value) and low <= value <= high):
        raise InputError(f"recipe field {name} must lie in [{low:g}, {high:g}], got {value!r}")


def check(r: Recipe) -> Recipe:
    """The recipe's fields in range and consistent with each other (each reason names the field), before any work."""
    if r.stage not in STAGES:
        raise InputError(f"recipe stage must be one of {', '.join(STAGES)}, not {r.stage!r}")
    if not 1 <= r.batch <= MAX_COUNT:
        raise InputError(f"recipe field batch must be between 1 and {MAX_COUNT}, got {r.batch}")
    if not r.batch <= r.buffer <= MAX_COUNT:
        raise InputError(f"recipe field buffer must hold at least batch = {r.batch} chains (at most {MAX_COUNT}), "
                         f"got {r.buffer}")
    if not (math.isfinite(r.lr) and 0.0 < r.lr <= 1.0):
        raise InputError(f"recipe field lr must be a learning rate above 0 and at most 1, got {r.lr!r}")
    if r.precision not in ("fp32", "bf16"):
        raise InputError(f"recipe field precision must be fp32 or bf16, not {r.precision!r}")
    if not 8 <= r.crop <= 4096:
        raise InputError(f"recipe field crop must be between 8 and 4096 cells, got {r.crop}")
    for name in ("focus", "cut", "turn", "distill"):
        _between(name, getattr(r, name), 0.0, 1.0)
    _between("free_weight", r.free_weight, 0.0, 1e6)
    if not (math.isfinite(r.val_every) and r.val_every > 0):
        raise InputError(f"recipe field val_every must be a number of minutes above 0, got {r.val_every!r}")
    if r.blend is not None and not (math.isfinite(r.blend) and 0.0 < r.blend < 1.0):
        raise InputError(f"recipe field blend must lie strictly between 0 and 1 (or be none), got {r.blend!r}")
    if r.channels is not None and not (r.channels and all(1 <= c <= 4096 for c in r.channels)):
        raise InputError(f"recipe field channels must be widths between 1 and 4096, got {r.channels}")
    if not r.coarse:
        used = [k for k in COARSE_ONLY if getattr(r, k) not in (0.0, False, None)]
        if used:
            raise InputError(f"recipe field {used[0]} is for the coarse stages, not {r.stage}")
    if r.stage == "autoencoder" and (r.free_space or r.init_from):
        raise InputError(f"recipe field {'free_space' if r.free_space else 'init_from'} is for the coarse and fine "
                         "stages (the autoencoder has neither)")
    if r.stage == "semantics" and r.free_space:
        raise InputError("recipe field free_space is not for the semantic head (it reads completed cells)")
    if r.placement is not None and (r.stage != "semantics" or r.placement not in SEMANTIC_PLACEMENTS):
        raise InputError(f"recipe field placement is the semantic head's input, one of "
                         f"{', '.join(SEMANTIC_PLACEMENTS)}" + ("" if r.stage == "semantics" else f", not for {r.stage}")
                         + f"; got {r.placement!r}")
    if r.steps is not None and not 1 <= r.steps <= 1000:
        raise InputError(f"recipe field steps must be between 1 and 1000 chain steps, got {r.steps}")
    if r.alpha1 is not None:
        _between("alpha1", r.alpha1, 0.0, 1.0)
    if (r.steps is not None or r.alpha1 is not None) and r.stage not in ("coarse", "coarse-noplanner", "fine"):
        raise InputError(f"recipe fields steps and alpha1 set the coarse and fine chains, not {r.stage}'s")
    if r.autoencoder and r.stage != "fine":
        raise InputError("recipe field autoencoder is for the fine stage")
    if r.free_weight and not r.free_space:
        raise InputError("recipe field free_weight weighs seen-empty cells: it needs free_space=true")
    if r.cut_free_loss and not (r.cut and r.free_weight):
        raise InputError("recipe field cut_free_loss weighs cut inputs' losses: it needs cut and free_weight")
    if r.distill and not (r.cut and r.free_space and r.init_from):
        raise InputError("recipe field distill acts on cut inputs with the free space, from the init_from weights: "
                         "it needs cut, free_space=true and init_from")
    if r.blend is not None and not r.init_from:
        raise InputError("recipe field blend mixes the run back toward its init_from weights: it needs init_from")
    if r.channels is not None and r.init_from:
        raise InputError("recipe field channels sets a new model's widths; init_from brings its own")
    return r


def resolve(name: str, sets: dict[str, Any]) -> Recipe:
    """The named recipe with `sets` applied, checked."""
    if name not in RECIPES:
        raise InputError(f"no recipe {name!r}; recipes: {', '.join(RECIPES)}")
    return check(dataclasses.replace(RECIPES[name], **sets))


def from_saved(saved: dict[str, Any]) -> Recipe:
    """The recipe a checkpoint saved (lists back to tuples)."""
    known = {f.name for f in dataclasses.fields(Recipe)}
    return Recipe(**{k: tuple(v) if isinstance(v, list) else v for k, v in saved.items() if k in known})


def resumed(saved: dict[str, Any], sets: dict[str, Any]) -> tuple[Recipe, dict[str, tuple[Any, Any]]]:
    """(the saved recipe with `sets` applied, {field: (was, now)} for each field they change). Fields that fix
    the model or the run's start are refused: a resume continues the run it names."""
    base = from_saved(saved)
    fixed = sorted(k for k in sets if k not in RESUMABLE and sets[k] != getattr(base, k))
    if fixed:
        raise InputError(f"--set {fixed[0]}: a resumed run keeps its {fixed[0]} ({getattr(base, fixed[0])!r}); "
                         f"start a new run (another --out) to change it")
    changed = {k: (getattr(base, k), v) for k, v in sets.items() if getattr(base, k) != v}
    return check(dataclasses.replace(base, **sets)), changed

"""The one weights module: every model file is written and read here, and `KINDS` says which classes each needs.

Files are torch zip archives that hold only tensors and plain values (dict, list, tuple, str, int, float, bool,
None), so every read is `torch.load(weights_only=True)`: a file holding anything else (a pickled object, whose
unpickling can run code) is refused before any of it becomes an object. Two layouts:

* weights (`hgca_core/weights/<stage>.pt`, written by `hgca train --export`):
  {"kind": KIND, "config": {...}, "state_dict": {name: fp16 or integer tensor}, "meta": {...}}; a fine file adds
  "autoencoder": {"config", "state_dict"}, the autoencoder its kernel was trained with (fp16 keeps the package
  small; loading gives float32);
* training checkpoints (runs/<stage>/ckpt.pt, `hgca_core.training.trainer`): {"task": KIND, "config", "model",
  "optim", "ema", "state", "ranks", ...}; a coarse checkpoint stands in for coarse weights.

A file of the wrong kind, or one whose config does not describe its tensors, is an `InputError` that says what
the file is and which option takes it, never a `load_state_dict` traceback.
"""
from __future__ import annotations

import errno
import math
import os
import pickle
import re
import stat
import warnings
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import torch
from torch import nn

from hgca_core.config import MAX_STEPS   # a weights file may ask for no longer a chain than a run may
from hgca_core.errors import InputError
from hgca_core.io.atomic import atomic_write
from hgca_core.io.digest import file_digest
from hgca_core.models.autoencoder import Autoencoder, AutoencoderConfig
from hgca_core.models.cgca import CGCAConfig, CGCAKernel
from hgca_core.models.config import Config
from hgca_core.models.gca import GCAConfig, GCAKernel
from hgca_core.models.semantics import SemanticHead, SemanticsConfig

WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights"


@dataclass(frozen=True)
class Kind:
    """What a kind of weights file needs to become a model, and how messages name it."""

    config: type[Config]
    model: type[nn.Module]
    label: str     # what the file holds, for messages
    option: str    # the command-line option that takes such a file


# coarse-noplanner is not a kind of its own: it is coarse weights whose config says use_planner = False.
KINDS: dict[str, Kind] = {
    "coarse": Kind(GCAConfig, GCAKernel, "coarse-stage weights (GCA kernel)", "`hgca complete --weights`"),
    "fine": Kind(CGCAConfig, CGCAKernel, "fine-stage weights (cGCA kernel with its autoencoder)",
                 "`hgca complete --fine-weights`"),
    "autoencoder": Kind(AutoencoderConfig, Autoencoder, "autoencoder weights (the fine stage's autoencoder alone)",
                        "`hgca train fine --autoencoder`"),
    "semantics": Kind(SemanticsConfig, SemanticHead, "semantic head weights (a class per 20 cm cell)",
                      "`hgca complete --semantics-weights`"),
}


def shipped(stage: str) -> Path:
    """The packaged weights of a stage: coarse, coarse-noplanner, autoencoder or fine."""
    return WEIGHTS_DIR / f"{stage.replace('-', '_')}.pt"


# -- writing ----------------------------------------------------------------------------------------------------
def save_file(obj: dict, path: str | os.PathLike) -> Path:
    """torch.save of plain contents, atomically (a crash never leaves half a file where a good one was)."""
    atomic_write(path, lambda f: torch.save(obj, f))
    return Path(path)


def weights_files(methods: list[str], coarse: str | os.PathLike | None = None, fine: str | os.PathLike | None = None,
                  noplanner: str | os.PathLike | None = None) -> dict[str, str]:
    """{role: path} of the files the evaluation `methods` run (coarse for hgca and hgca-full, fine for hgca-full,
    noplanner for gca), each the one given or else the shipped file: the one place that decides it, for loading
    and for the record of what was loaded."""
    roles = {"coarse": (("hgca", "hgca-full"), coarse, "coarse"), "fine": (("hgca-full",), fine, "fine"),
             "noplanner": (("gca",), noplanner, "coarse-noplanner")}
    return {r: str(given or shipped(stage)) for r, (ms, given, stage) in roles.items() if set(ms) & set(methods)}


def weights_record(methods: list[str], coarse: str | os.PathLike | None = None, fine: str | os.PathLike | None = None,
                   noplanner: str | os.PathLike | None = None) -> dict:
    """{"weights": role -> path, "weights_sha256": role -> digest} of `weights_files`: a results file names its
    weights by content, so runs that are pooled or resumed are checked to be of the same weights, not merely of
    the same path."""
    files = weights_files(methods, coarse, fine, noplanner)
    return {"weights": files, "weights_sha256": {r: file_digest(f) for r, f in files.items()}}


def shown_path(path: str | os.PathLike) -> str:
    """`path` as a weights record names it: relative to the repository when it lies inside (a record must not
    carry one machine's absolute paths), else as given."""
    root = WEIGHTS_DIR.parents[1]
    try:
        return str(Path(path).resolve().relative_to(root))
    except ValueError:
        return str(path)


# -- reading ----------------------------------------------------------------------------------------------------
def load_file(path: str | os.PathLike, hint: str = "") -> dict:
    """The plain contents of a weights file or checkpoint, read without running anything from it.

    Every failure is an `InputError` naming the file: missing, a folder, unreadable, not a torch file, or a
    file holding pickled objects (refused, nothing from it was run)."""
    p = Path(path)
    _check_regular(p, hint)
    try:
        with warnings.catch_warnings():  # torch warns about pickle protocols of foreign files: the error says it
            warnings.simplefilter("ignore")
            blob = torch.load(p, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:   # the weights_only unpickler stopped before building anything
        named = re.search(r"GLOBAL ([\w.]+)", str(exc))
        if named:
            raise InputError(f"refused: it holds pickled Python objects ({named.group(1)}), not only tensors and plain "
                             "values; nothing from it was run", str(p)) from None
        raise InputError("not a readable hgca weights file (not a plain torch file: corrupt, another format or "
                         "pickled objects); nothing from it was run", str(p)) from None
    except PermissionError:
        raise InputError("cannot read the weights file (permission denied)", str(p)) from None
    except Exception as exc:  # truncated, empty, another format
        raise InputError(f"not a readable hgca weights file ({exc.__class__.__name__}: corrupt, truncated or "
                         "another format)", str(p)) from None
    if not isinstance(blob, dict):
        raise InputError(f"not an hgca weights file (it holds a {type(blob).__name__}, not a dict)", str(p))
    return blob


def _check_regular(p: Path, hint: str) -> None:
    """Say what `p` is when it is not a regular file, before opening it: a FIFO would block the read forever."""
    try:
        st = os.stat(p)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise InputError("the weights file is a symbolic link loop", str(p)) from None
        if os.path.islink(p):
            raise InputError(f"the weights file is a symbolic link to a missing target ({os.readlink(p)})",
                             str(p)) from None
        if exc.errno == errno.ENOENT:
            raise InputError(f"no such weights file{hint}", str(p)) from None
        raise InputError(f"cannot open the weights file ({exc.strerror})", str(p)) from None
    except ValueError as exc:   # NUL in the name
        raise InputError(f"the weights file name is not a valid path ({exc})", str(p)) from None
    if stat.S_ISDIR(st.st_mode):
        raise InputError("is a folder, not a weights file", str(p))
    if not stat.S_ISREG(st.st_mode):
        raise InputError("the weights file is not a regular file (a pipe, device or socket)", str(p))


# Bounds of the config values a weights file may hold: what this code can run in reasonable time and memory.
# Steps are network passes per sample (the shipped files use 30 and 15); 10^9 would never end.
INT_BOUNDS = {"steps": (1, MAX_STEPS), "channels": (1, 4096), "grid": (1, 65536)}
DEFAULT_INT_BOUNDS = (0, 65536)
FLOAT_BOUND = 1e6


MAX_CONFIG_NESTING = 4


def _nesting(value: Any, limit: int = MAX_CONFIG_NESTING + 1) -> int:
    """How deeply lists, tuples and dicts nest in `value`, counted without recursion and only up to `limit` (a
    file may hold 100,000 nested lists)."""
    level, frontier = 0, [value]
    while frontier and level <= limit:
        children = []
        for v in frontier:
            if isinstance(v, dict):
                children.extend(v.values())
            elif isinstance(v, (list, tuple)):
                children.extend(v)
        if not children:
            break
        level, frontier = level + 1, children[:4096]
    return level


def check_config(config: dict, kind: str, what: str, path: str) -> None:
    """Refuse config values of the wrong type or out of bounds (a string "30" for steps, 10^9 steps, NaN), with
    the key, before any model is built. Types come from the dataclass defaults; unknown keys are ignored."""
    fields = KINDS[kind].config.__dataclass_fields__  # type: ignore[attr-defined]
    for key, value in config.items():
        if _nesting(value) > MAX_CONFIG_NESTING:
            raise InputError(f"the {what}config's {key!r} is nested more than {MAX_CONFIG_NESTING} levels deep: "
                             "not a model config (a config holds numbers, names and short lists)", path)
        if key not in fields:
            continue
        default = fields[key].default
        low, high = INT_BOUNDS.get(key, DEFAULT_INT_BOUNDS)
        problem = ""
        if isinstance(default, bool):
            problem = "" if isinstance(value, bool) else "must be true or false"
        elif isinstance(default, int) or (default is None and key == "crop"):
            if value is None and (default is None or key == "crop"):   # crop None: the trainer's whole-scene crops
                continue
            if isinstance(value, bool) or not isinstance(value, int):
                problem = "must be a whole number"
            elif not low <= value <= high:
                problem = f"must be between {low} and {high}"
        elif isinstance(default, float):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                problem = "must be a number"
            elif not math.isfinite(value) or abs(value) > FLOAT_BOUND:
                problem = f"must be a finite number within +-{FLOAT_BOUND:g}"
        elif isinstance(default, str):
            problem = "" if isinstance(value, str) else "must be a string"
        elif isinstance(default, tuple):
            if not isinstance(value, (list, tuple)) or not value or len(value) > 64 or any(
                    isinstance(v, bool) or not isinstance(v, int) or not low <= v <= high for v in value):
                problem = f"must be a list of whole numbers between {low} and {high}"
        if problem:
            raise InputError(f"the {what}config does not describe a {kind} model: its {key!r} {problem}, got "
                             f"{value!r}", path)


def check_finite(state_dict: dict[str, torch.Tensor], what: str, path: str) -> None:
    """Refuse tensors holding NaN or infinity, and BatchNorm running variances below zero: such weights load but
    give an empty or meaningless mesh with exit 0."""
    for name, t in state_dict.items():
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            bad = int((~torch.isfinite(t)).sum())
            raise InputError(f"the {what}tensor {name!r} holds {bad} NaN or infinite value(s) of {t.numel()}: "
                             "the file is corrupt", path)
        if name.endswith("running_var") and t.is_floating_point() and bool((t < 0).any()):
            raise InputError(f"the {what}tensor {name!r} holds {int((t < 0).sum())} negative variance(s): a "
                             "BatchNorm variance is never below zero, so the file is corrupt", path)


def identify(blob: dict) -> tuple[str | None, bool]:
    """(kind, is a training checkpoint) of a file's contents; kind None when it is neither."""
    if blob.get("kind") in KINDS and "state_dict" in blob:
        return blob["kind"], False
    if blob.get("task") in KINDS and "model" in blob:
        return blob["task"], True
    return None, False


def trained_weights(ck: dict) -> dict[str, torch.Tensor]:
    """The weights to ship or evaluate from a training checkpoint: the weight average when it has one."""
    return ck["ema"]["model"] if ck.get("ema") else ck["model"]


def _wrong_kind(path: str, found: str | None, checkpoint: bool, want: str) -> InputError:
    wanted = f"{KINDS[want].option} takes {KINDS[want].label}"
    if found is None:
        return InputError(f"not an hgca weights file or training checkpoint (no known 'kind'); {wanted}", path)
    if checkpoint:
        how = ("`hgca train --export` turns it into weights" if found != "coarse" else
               f"{KINDS['coarse'].option} takes it")
        return InputError(f"this is a {found} training checkpoint ({how}); {wanted}", path)
    return InputError(f"this file holds {KINDS[found].label}, which {KINDS[found].option} takes; {wanted}", path)


def _shape_problems(expected: dict[str, torch.Tensor], got: dict[str, Any]) -> str:
    """'' when `got` has exactly the names and shapes of `expected`, else a short account of the differences."""
    missing = [k for k in expected if k not in got]
    extra = [k for k in got if k not in expected]
    wrong = [k for k in expected if k in got and tuple(got[k].shape) != tuple(expected[k].shape)]
    parts = [f"{len(missing)} missing (e.g. {missing[0]})" if missing else "",
             f"{len(extra)} unknown (e.g. {extra[0]})" if extra else "",
             f"{len(wrong)} of another shape (e.g. {wrong[0]}: file {tuple(got[wrong[0]].shape)}, config "
             f"{tuple(expected[wrong[0]].shape)})" if wrong else ""]
    return ", ".join(p for p in parts if p)


def build(kind: str, config: Any, state_dict: Any, path: str, part: str = "") -> nn.Module:
    """An eval-mode float32 model of `kind` on the CPU from a config dict and a state dict, checked first.

    The model is built on the meta device before any memory is spent, so a config that does not describe the
    file's tensors (edited, garbled, from another version) is reported, not loaded."""
    what = f"{part} " if part else ""
    if not isinstance(config, dict) or not config:
        raise InputError(f"the {what}config is {'empty' if isinstance(config, dict) or config is None else 'not a dict'}"
                         f": cannot tell which {kind} model the tensors belong to", path)
    if not isinstance(state_dict, dict) or not state_dict or not all(
            isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state_dict.items()):
        raise InputError(f"the {what}state_dict is not a non-empty table of named tensors", path)
    k = KINDS[kind]
    check_config(config, kind, what, path)
    check_finite(state_dict, what, path)
    try:
        cfg = k.config.from_dict(config)
        with torch.device("meta"):
            expected = k.model(cfg).state_dict()
    except Exception as exc:
        raise InputError(f"the {what}config does not describe a {kind} model ({exc.__class__.__name__}: {exc})",
                         path) from None
    problems = _shape_problems(expected, state_dict)
    if problems:
        raise InputError(f"the {what}tensors do not fit the {kind} model the config describes: {problems}", path)
    model = k.model(cfg)
    model.load_state_dict({n: (v.float() if v.is_floating_point() else v) for n, v in state_dict.items()})
    return model.eval()


def _read(path: str | os.PathLike | None, want: str, default_stage: str) -> tuple[str, dict]:
    """(path as text, contents) of the file for `want`, the packaged one when `path` is None."""
    p = str(path if path is not None else shipped(default_stage))
    hints = {"coarse": " (train one with `hgca train coarse --export`, or pass --weights)",
             "fine": " (train them with `hgca train fine --export`, or pass --fine-weights; or use --stage coarse)",
             "autoencoder": " (train one with `hgca train autoencoder --export`, or pass --autoencoder)",
             "semantics": " (train one with `hgca train --recipe semantics --export`, or pass --semantics-weights)"}
    return p, load_file(p, hints[want])


Key = tuple[str, str, int, int]


def _cache_key(path: str | os.PathLike | None, default_stage: str) -> Key:
    """(path as given, resolved path, mtime, size): a file rewritten in place is read again, not served from
    the cache; messages name the path the way the user wrote it."""
    p = Path(path if path is not None else shipped(default_stage))
    try:
        st = p.stat()
        return str(p), str(p.resolve()), st.st_mtime_ns, st.st_size
    except OSError:
        return str(p), str(p), -1, -1   # load_file reports it


def _meta(blob: dict) -> dict:
    return blob["meta"] if isinstance(blob.get("meta"), dict) else {}


def _checkpoint_meta(blob: dict, kind: str, path: str) -> dict:
    """What a training checkpoint says of its run, in a weights file's meta terms (steps, wall time, sessions,
    notes, start), for `load_coarse` and `load_into` alike."""
    state = blob.get("state") if isinstance(blob.get("state"), dict) else {}
    return {"kind": kind, "steps": state.get("step"), "checkpoint": path,
            **({"train_wall_s": round(state["elapsed_s"], 1)} if "elapsed_s" in state else {}),
            **{k: state[k] for k in ("sessions", "notes", "init") if k in state}}


def load_coarse(path: str | os.PathLike | None = None, device: str | torch.device = "cpu") -> tuple[GCAKernel, dict]:
    """(coarse kernel in eval mode, float32, on `device`; meta) from weights or a coarse training checkpoint
    (default: the packaged coarse.pt); cached per file and device."""
    return _load_coarse(_cache_key(path, "coarse"), str(device))


@lru_cache(maxsize=4)
def _load_coarse(key: Key, device: str) -> tuple[GCAKernel, dict]:
    path, blob = _read(key[0], "coarse", "coarse")
    kind, checkpoint = identify(blob)
    if kind != "coarse":
        raise _wrong_kind(path, kind, checkpoint, "coarse")
    if checkpoint:
        sd = {k.removeprefix("model."): v for k, v in trained_weights(blob).items()}
        meta = _checkpoint_meta(blob, "coarse", path)
    else:
        sd, meta = blob["state_dict"], _meta(blob)
    return build("coarse", blob.get("config"), sd, path).to(device), meta


def load_fine(path: str | os.PathLike | None = None,
              device: str | torch.device = "cpu") -> tuple[CGCAKernel, Autoencoder, dict]:
    """(cGCA kernel, its autoencoder, meta), eval mode, float32, on `device` (default: the packaged fine.pt);
    cached per file and device."""
    return _load_fine(_cache_key(path, "fine"), str(device))


@lru_cache(maxsize=4)
def _load_fine(key: Key, device: str) -> tuple[CGCAKernel, Autoencoder, dict]:
    path, blob = _read(key[0], "fine", "fine")
    kind, checkpoint = identify(blob)
    if kind != "fine" or checkpoint:
        raise _wrong_kind(path, kind, checkpoint, "fine")
    ae = blob.get("autoencoder")
    if not isinstance(ae, dict):
        raise InputError("fine-stage weights without their autoencoder (no 'autoencoder' entry): the file is "
                         "incomplete", path)
    model = build("fine", blob.get("config"), blob["state_dict"], path)
    autoencoder = build("autoencoder", ae.get("config"), ae.get("state_dict"), path, part="autoencoder")
    if autoencoder.cfg.latent != model.cfg.latent:
        raise InputError(f"the kernel's latent size {model.cfg.latent} differs from its autoencoder's "
                         f"{autoencoder.cfg.latent}", path)
    return model.to(device), autoencoder.to(device), _meta(blob)


def load_autoencoder(path: str | os.PathLike | None = None, device: str | torch.device = "cpu") -> Autoencoder:
    """The autoencoder of autoencoder weights (default: the packaged autoencoder.pt), eval mode, on `device`."""
    path, blob = _read(path, "autoencoder", "autoencoder")
    kind, checkpoint = identify(blob)
    if kind != "autoencoder" or checkpoint:
        raise _wrong_kind(path, kind, checkpoint, "autoencoder")
    return build("autoencoder", blob.get("config"), blob["state_dict"], path).to(device)


def load_semantics(path: str | os.PathLike | None = None, device: str | torch.device = "cpu") -> SemanticHead:
    """The semantic head (`hgca_core.models.semantics`) of semantics weights or a semantics training checkpoint
    (default: the packaged semantics.pt), eval mode, float32, on `device`; cached per file and device."""
    return _load_semantics(_cache_key(path, "semantics"), str(device))


@lru_cache(maxsize=4)
def _load_semantics(key: Key, device: str) -> SemanticHead:
    path, blob = _read(key[0], "semantics", "semantics")
    kind, checkpoint = identify(blob)
    if kind != "semantics":
        raise _wrong_kind(path, kind, checkpoint, "semantics")
    sd = ({k.removeprefix("model."): v for k, v in trained_weights(blob).items() if k.startswith("model.")}
          if checkpoint else blob["state_dict"])
    return build("semantics", blob.get("config"), sd, path).to(device)

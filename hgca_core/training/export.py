"""Writing weights files from training: a model as weights of its kind (`hgca train --export`), blends of two
files (WiSE-FT), the lineage a file made from others keeps, and warm starts (`--init-from`). Reading and checking
files is `hgca_core.models.weights`, the one module that calls torch.load / torch.save; this one writes through its
`save_file`, so a completion never imports training code."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch
from torch import nn

from hgca_core.errors import InputError
from hgca_core.io.digest import file_digest
from hgca_core.models.autoencoder import Autoencoder
from hgca_core.models.weights import (KINDS, _checkpoint_meta, _meta, build, identify, load_file, save_file,
                                      shown_path, trained_weights)


def kind_of(model: nn.Module) -> str:
    for name, k in KINDS.items():
        if type(model) is k.model:
            return name
    raise TypeError(f"no weights kind for {type(model).__name__}")


def half_state(module: nn.Module) -> dict[str, torch.Tensor]:
    """fp16 copies of the floating tensors (integer buffers such as BatchNorm counters stay as they are), on CPU."""
    return {k: (v.half() if v.is_floating_point() else v).cpu() for k, v in module.state_dict().items()}


def save_weights(path: str | os.PathLike, model: nn.Module, meta: dict[str, Any] | None = None,
                 autoencoder: Autoencoder | None = None) -> Path:
    """Write `model` as weights of its kind; fine weights need the autoencoder the kernel was trained with."""
    kind = kind_of(model)
    blob: dict[str, Any] = {"kind": kind, "config": model.cfg.to_dict(), "state_dict": half_state(model),
                            "meta": {**(meta or {}), "kind": kind}}
    if kind == "fine":
        if autoencoder is None:
            raise ValueError("fine weights need the autoencoder their kernel was trained with")
        blob["autoencoder"] = {"config": autoencoder.cfg.to_dict(), "state_dict": half_state(autoencoder)}
    return save_file(blob, path)


def blend_files(a: str | os.PathLike, b: str | os.PathLike, t: float) -> dict:
    """Weights `(1 - t) * a + t * b`, tensor by tensor: a fine-tune interpolated back toward the weights it started
    from (WiSE-FT, Wortsman et al. 2022), which keeps more of the fine-tune's gain off its training distribution.

    Both files must be weights (not checkpoints) of the same kind and architecture, fine ones over the same
    autoencoder (kept as it is); the result takes `a`'s config except the chain's schedule (`SCHEDULE`), which is
    `b`'s: `b` is the fine-tune, and a few-step student blended back toward its teacher samples the short chain it
    was trained for. Both sources are recorded in its meta.
    Floating tensors are mixed in fp32, integer buffers are `a`'s."""
    if not 0.0 <= t <= 1.0:
        raise ValueError(f"blend fraction {t} is outside [0, 1]")
    blobs = [load_file(f) for f in (a, b)]
    for f, blob in zip((a, b), blobs):
        kind, checkpoint = identify(blob)
        if kind is None or checkpoint:
            raise InputError("not an hgca weights file (export a checkpoint with `hgca train --export` first)", str(f))
    ka, kb = blobs[0]["kind"], blobs[1]["kind"]
    if ka != kb or _architecture(ka, blobs[0]) != _architecture(kb, blobs[1]):
        raise InputError(f"cannot blend: {ka} and {kb} weights of different architectures", str(b))
    if not _same_autoencoder(blobs[0], blobs[1]):
        raise InputError("cannot blend: fine weights with different autoencoders (a latent of one means nothing "
                         "to the other's decoder)", str(b))
    sa, sb = blobs[0]["state_dict"], blobs[1]["state_dict"]
    if sa.keys() != sb.keys() or any(sa[k].shape != sb[k].shape for k in sa):
        raise InputError("cannot blend: the files' tensors differ in names or shapes", str(b))
    state = {k: (((1 - t) * v.float() + t * sb[k].float()).to(v.dtype) if v.is_floating_point() else v)
             for k, v in sa.items()}
    meta = {**_meta(blobs[0]), "blend": {"t": t, "a": lineage(a, _meta(blobs[0])), "b": lineage(b, _meta(blobs[1]))}}
    config = {**blobs[0]["config"], **{k: v for k, v in blobs[1]["config"].items() if k in SCHEDULE}}
    return {**blobs[0], "config": config, "state_dict": state, "meta": meta}


def _same_autoencoder(a: dict, b: dict) -> bool:
    """Whether two weights blobs carry the same autoencoder (or none): fine weights blend only over one decoder,
    as a fine student's, which trains with its teacher's autoencoder frozen."""
    ea, eb = a.get("autoencoder"), b.get("autoencoder")
    if ea is None or eb is None:
        return ea is eb
    sa, sb = ea["state_dict"], eb["state_dict"]
    return (ea.get("config") == eb.get("config") and sa.keys() == sb.keys()
            and all(sa[k].shape == sb[k].shape and torch.equal(sa[k], sb[k]) for k in sa))


LINEAGE_KEYS = ("steps", "train_wall_s", "data", "seed", "sessions", "notes", "blend", "init")


def lineage(path: str | os.PathLike, meta: dict) -> dict:
    """The record of the weights at `path` that a file made from them keeps (a blend's two sources, a run's
    `--init-from`): content digest, steps, wall time, data, seed, sessions and notes, and their own blend or start,
    nested. Why: a file's card must name every session and device its tensors come from, not only the last
    run's (a blend of a blend, or a fine-tune of one, would otherwise lose the earlier hardware and steps)."""
    return {"file": shown_path(path), "sha256": file_digest(path), **{k: meta[k] for k in LINEAGE_KEYS if k in meta}}


SCHEDULE = ("steps", "alpha0", "alpha1")   # the chain a coarse file samples (T1 and the infusion slope)


def _architecture(kind: str, blob: dict) -> dict:
    """The config as this version reads it (fields a file predates filled in), less the sampling settings
    (`keep`, `bias` and the chain's `SCHEDULE`), which do not change the tensors."""
    cfg = KINDS[kind].config.from_dict(blob["config"]).to_dict()
    return {k: v for k, v in cfg.items() if k not in ("keep", "bias", *SCHEDULE)}


# -- warm start -------------------------------------------------------------------------------------------------
def load_into(model: nn.Module, path: str | os.PathLike) -> dict:
    """Initialise `model` from the weights or training checkpoint at `path` (`hgca train --init-from`); returns
    the file's meta ({"steps", "checkpoint"} for a checkpoint) with "widened": the tensors that gained columns.

    Every tensor must have the file's shape, except where the model reads inputs the file's model did not have
    (`model.free_columns()`: the observed-free-space columns): there the file's weights are copied into the
    other columns and the new ones start at zero, so the new model computes exactly what the file's did until
    training moves them (up to float rounding of the wider sums). Anything else that does not fit (another
    architecture, another kind of model) is an `InputError` naming the file."""
    kind, p = kind_of(model), str(path)
    blob = load_file(p, " (--init-from takes weights or a training checkpoint)")
    found, checkpoint = identify(blob)
    if found != kind:
        what = f"a {found} {'training checkpoint' if checkpoint else 'weights file'}" if found else \
            "not an hgca weights file or training checkpoint"
        raise InputError(f"--init-from of a {kind} model needs {KINDS[kind].label} or its training checkpoint; "
                         f"this is {what}", p)
    if checkpoint:
        sd = {k.removeprefix("model."): v for k, v in trained_weights(blob).items()}
        meta = _checkpoint_meta(blob, kind, p)
    else:
        sd, meta = blob["state_dict"], _meta(blob)
    source = build(kind, blob.get("config"), sd, p).state_dict()   # the file is consistent in itself
    model.load_state_dict(widened(source, model, p))
    return {**meta, "widened": sorted(k for k, v in model.state_dict().items() if v.shape != source[k].shape)}


def widened(source: dict[str, torch.Tensor], model: nn.Module, path: str = "") -> dict[str, torch.Tensor]:
    """`source` (a state dict) fitted to `model`: equal shapes copied, new free-space input columns zero."""
    cols = model.free_columns() if hasattr(model, "free_columns") else {}
    target = model.state_dict()
    out, problems = {}, []
    for name, t in target.items():
        s = source.get(name)
        if s is None:
            problems.append(f"{name} missing")
        elif s.shape == t.shape:
            out[name] = s.to(t.dtype)
        elif name in cols:
            dim, new = cols[name]
            keep = [i for i in range(t.shape[dim]) if i not in new]
            expect = list(t.shape)
            expect[dim] = len(keep)
            if list(s.shape) != expect:
                problems.append(f"{name}: file {tuple(s.shape)}, model {tuple(t.shape)}")
                continue
            w = torch.zeros_like(t)
            w.index_copy_(dim, torch.tensor(keep, dtype=torch.long), s.to(t.dtype))
            out[name] = w
        else:
            problems.append(f"{name}: file {tuple(s.shape)}, model {tuple(t.shape)}")
    problems += [f"{name} unknown to the model" for name in source if name not in target]
    if problems:
        raise InputError(f"cannot start this {kind_of(model)} model from the file: its tensors do not fit "
                         f"({len(problems)}: {'; '.join(problems[:3])}); only the observed-free-space inputs may "
                         "be new", path or None)
    return out

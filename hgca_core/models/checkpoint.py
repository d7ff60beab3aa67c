"""Shipped weights: config + fp16 state dict + metadata in one torch file, loaded back to float32."""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Any

import torch

from hgca_core.errors import InputError
from hgca_core.models.gca import GCAConfig, GCAKernel

WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights"


def save_weights(model: torch.nn.Module, cfg_dict: dict, path: str | Path, meta: dict[str, Any]) -> None:
    """fp16 storage keeps the package small; integer buffers (BatchNorm counters) stay as they are."""
    sd = {k: (v.half() if v.is_floating_point() else v) for k, v in model.state_dict().items()}
    path = Path(path)
    tmp = path.with_suffix(".tmp")
    torch.save({"kind": meta.get("kind", "coarse"), "config": cfg_dict, "state_dict": sd, "meta": meta}, tmp)
    tmp.replace(path)


def read_weights(path: str | Path) -> dict:
    path = Path(path)
    if not path.exists():
        raise InputError(f"no weights file (train one with `hgca train`, or pass --weights)", str(path))
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # a truncated or foreign file
        raise InputError(f"not a readable hgca weights file ({exc.__class__.__name__})", str(path)) from exc


@lru_cache(maxsize=4)
def load_coarse(path: str, device: str = "cpu") -> tuple[GCAKernel, dict]:
    """The coarse kernel in eval mode, float32, on `device`; cached per (path, device)."""
    blob = read_weights(path)
    if "state_dict" in blob:
        sd, meta = blob["state_dict"], blob["meta"]
    elif "model" in blob and "config" in blob:  # a training checkpoint (runs/<stage>/ckpt.pt) works too
        from hgca_core.training.trainer import trained_weights

        sd = {k.removeprefix("model."): v for k, v in trained_weights(blob).items()}
        meta = {"kind": "coarse", "steps": blob["state"]["step"], "checkpoint": str(path)}
    else:
        raise InputError("not an hgca weights file or training checkpoint", str(path))
    model = GCAKernel(GCAConfig.from_dict(blob["config"]))
    model.load_state_dict({k: (v.float() if v.is_floating_point() else v) for k, v in sd.items()})
    return model.to(device).eval(), meta

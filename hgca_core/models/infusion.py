"""The infusion schedule both chains train with (GCA and cGCA; paper Sec. 3.1 and App.: alpha_t = 0.15 + 0.005 t):
per cell, the infusion kernel is Ber((1 - alpha_t) lambda + alpha_t [c in gt]). One function, so the two stages
cannot drift apart."""
from __future__ import annotations

from typing import Protocol


class InfusionConfig(Protocol):
    """What the schedule reads from a model config (`GCAConfig` and `CGCAConfig` both have it)."""

    alpha0: float
    alpha1: float


def alpha(cfg: InfusionConfig, t: int) -> float:
    """Infusion weight alpha_t = alpha0 + alpha1 * t, clipped to [0, 1]."""
    return float(min(max(cfg.alpha0 + cfg.alpha1 * t, 0.0), 1.0))

"""Persistent chains for infusion training (paper Sec. 3.1, Eq. 4-5).

Each chain holds an example (s^0, s^gt) and its current infusion state s~^t. A training step advances the
chains it used by one infusion transition; a chain that reaches T steps (or dies out) restarts from a fresh
example at t = 0. Keeping chains across steps means every step trains on states from the whole range of t
without re-simulating the chain from scratch.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import torch


@dataclass
class Chain:
    s0: torch.Tensor       # (N, 3) int64
    gt: torch.Tensor       # (M, 3) int64
    state: torch.Tensor    # (K, 3) int64
    t: int
    grid: tuple[int, int, int]
    extra: dict | None = None


def _moved(x: Any, device: torch.device | str) -> Any:
    """`x` with every tensor in it (dicts of tensors included) on `device`."""
    if isinstance(x, torch.Tensor):
        return x.to(device)
    if isinstance(x, dict):
        return {k: _moved(v, device) for k, v in x.items()}
    return x


class ChainBuffer:
    """The chains of one rank, kept on the training device: examples are made on the CPU (like a data loader's
    work) and moved there once, when they enter the buffer."""

    def __init__(self, size: int, new_example: Callable[[np.random.Generator], Chain], max_steps: int,
                 rng: np.random.Generator, device: torch.device | str = "cpu") -> None:
        self.size, self.new_example, self.max_steps, self.rng = size, new_example, max_steps, rng
        self.device = torch.device(device)
        self.chains: list[Chain] = []
        self.cursor = 0

    def _fresh(self) -> Chain:
        ch = self.new_example(self.rng)
        return Chain(ch.s0.to(self.device), ch.gt.to(self.device), ch.state.to(self.device), ch.t, ch.grid,
                     _moved(ch.extra, self.device))

    def take(self, n: int) -> list[int]:
        """Indices of the next n chains (round robin), filling the buffer lazily."""
        while len(self.chains) < self.size:
            self.chains.append(self._fresh())
        idx = [(self.cursor + i) % self.size for i in range(n)]
        self.cursor = (self.cursor + n) % self.size
        return idx

    def advance(self, i: int, new_state: torch.Tensor, extra: dict | None = None) -> None:
        ch = self.chains[i]
        ch.t += 1
        if ch.t >= self.max_steps or len(new_state) == 0:
            self.chains[i] = self._fresh()
        else:
            ch.state = new_state
            if extra is not None:
                ch.extra = extra

    def state_dict(self) -> dict:
        """Plain contents (CPU tensors, ints, the numpy generator's state dict) for a weights_only checkpoint."""
        return {"cursor": self.cursor, "rng": self.rng.bit_generator.state,
                "chains": [{"s0": c.s0.to("cpu", torch.int32), "gt": c.gt.to("cpu", torch.int32),
                            "state": c.state.to("cpu", torch.int32), "t": c.t, "grid": list(c.grid),
                            "extra": _moved(c.extra, "cpu")} for c in self.chains]}

    def load_state_dict(self, d: dict) -> None:
        self.cursor = d["cursor"]
        self.rng.bit_generator.state = d["rng"]
        dev = self.device
        self.chains = [Chain(c["s0"].to(dev, torch.long), c["gt"].to(dev, torch.long), c["state"].to(dev, torch.long),
                             c["t"], tuple(c["grid"]), _moved(c["extra"], dev)) for c in d["chains"]]

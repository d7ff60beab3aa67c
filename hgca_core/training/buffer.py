"""Persistent chains for infusion training (paper Sec. 3.1, Eq. 4-5).

Each chain holds an example (s^0, s^gt) and its current infusion state s~^t. A training step advances the
chains it used by one infusion transition; a chain that reaches T steps (or dies out) restarts from a fresh
example at t = 0. Keeping chains across steps means every step trains on states from the whole range of t
without re-simulating the chain from scratch.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

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


class ChainBuffer:
    def __init__(self, size: int, new_example: Callable[[np.random.Generator], Chain], max_steps: int,
                 rng: np.random.Generator) -> None:
        self.size, self.new_example, self.max_steps, self.rng = size, new_example, max_steps, rng
        self.chains: list[Chain] = []
        self.cursor = 0

    def take(self, n: int) -> list[int]:
        """Indices of the next n chains (round robin), filling the buffer lazily."""
        while len(self.chains) < self.size:
            self.chains.append(self.new_example(self.rng))
        idx = [(self.cursor + i) % self.size for i in range(n)]
        self.cursor = (self.cursor + n) % self.size
        return idx

    def advance(self, i: int, new_state: torch.Tensor, extra: dict | None = None) -> None:
        ch = self.chains[i]
        ch.t += 1
        if ch.t >= self.max_steps or len(new_state) == 0:
            self.chains[i] = self.new_example(self.rng)
        else:
            ch.state = new_state
            if extra is not None:
                ch.extra = extra

    def state_dict(self) -> dict:
        return {"cursor": self.cursor, "rng": self.rng.bit_generator.state,
                "chains": [{"s0": c.s0.to(torch.int32), "gt": c.gt.to(torch.int32), "state": c.state.to(torch.int32),
                            "t": c.t, "grid": c.grid, "extra": c.extra} for c in self.chains]}

    def load_state_dict(self, d: dict) -> None:
        self.cursor = d["cursor"]
        self.rng.bit_generator.state = d["rng"]
        self.chains = [Chain(c["s0"].long(), c["gt"].long(), c["state"].long(), c["t"], tuple(c["grid"]), c["extra"])
                       for c in d["chains"]]

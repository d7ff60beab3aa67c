"""How an evaluation completes its inputs, read once from the command line by `hgca eval` / `hgca eval-real`, so
the scoring code takes plain values and never an argparse namespace (the library can be driven without the CLI)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, kw_only=True)
class EvalSettings:
    """The completions an evaluation scores: k samples per input (sample i uses seed + i), the GCA step counts
    (None: the weights' own), the GEMM precision and the free-space mode (as `hgca complete`)."""

    samples: int
    seed: int
    t1: int | None
    t2: int | None
    precision: str
    free_space: str


@dataclass(frozen=True, kw_only=True)
class RealEvalSettings(EvalSettings):
    """`hgca eval-real`'s settings besides the completions': the weights of each role (None: the shipped file),
    the full stage's own sample count (None: `samples`), the Poisson baseline's threads and the region's yaw."""

    weights: str | None
    fine_weights: str | None
    noplanner_weights: str | None
    full_samples: int | None
    threads: int
    yaw: float

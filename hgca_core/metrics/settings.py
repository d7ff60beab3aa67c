"""How `hgca eval-real` completes its inputs, read once from the command line, so the scoring code takes plain
values and never an argparse namespace (the library can be driven without the CLI). The completions themselves
are a `CompletionConfig`, as for `hgca complete` and `hgca eval`."""
from __future__ import annotations

from dataclasses import dataclass

from hgca_core.config import CompletionConfig


@dataclass(frozen=True, kw_only=True)
class RealEvalSettings:
    """`hgca eval-real`'s settings: each completion's config (`completion`: k samples per input, sample i uses
    seed + i, the step counts, precision, free space and the weights of the hgca rows, None: the shipped files),
    the GCA baseline's weights, the full stage's own sample count (None: `completion.samples`), the Poisson
    baseline's threads and the region's yaw."""

    completion: CompletionConfig
    noplanner_weights: str | None
    full_samples: int | None
    threads: int
    yaw: float

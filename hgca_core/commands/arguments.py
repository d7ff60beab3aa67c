"""Argument types and checks shared by the commands, so a flag out of range fails while parsing or before any
work, with the flag's name, and never as an overflow or a traceback minutes later.

Parsing types (`argparse` calls them) turn a bad value into `hgca CMD: error: argument --flag: ...`, exit 2.
Checks of combinations (a seed plus its samples, a stride from size and overlap) raise `InputError`.
Nothing here imports torch: parsing must stay fast.
"""
from __future__ import annotations

import argparse
import math
import re
from typing import Callable

from hgca_core.errors import InputError

# The bounds of pipeline.SEED_MAX, pipeline.MIN_FACES and models.weights.MAX_STEPS, spelt out so that parsing
# arguments does not import torch (a test holds them equal).
SEED_MAX = 2**63 - 1
MIN_FACES = 1000
MAX_STEPS = 1000
MAX_SAMPLES = 1000
MAX_WORKERS = 4096


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None


def seed_arg(text: str) -> int:
    """`--seed`: a whole number in [0, 2**63 - 1]."""
    value = _int(text)
    if not 0 <= value <= SEED_MAX:
        raise argparse.ArgumentTypeError(f"must be between 0 and 2**63 - 1 = {SEED_MAX}, got {value}")
    return value


def counted(low: int, high: int | None = None) -> Callable[[str], int]:
    """A type for a count in [low, high] (`--samples`, `--workers`, `--count`, ...)."""
    def parse(text: str) -> int:
        value = _int(text)
        if value < low or (high is not None and value > high):
            span = f"at least {low}" if high is None else f"between {low} and {high}"
            raise argparse.ArgumentTypeError(f"must be {span}, got {value}")
        return value
    parse.__name__ = "count"
    return parse


samples_arg = counted(1, MAX_SAMPLES)


def max_faces_arg(text: str) -> int:
    """`--max-faces`: 0 (keep every triangle) or at least MIN_FACES."""
    value = _int(text)
    if value != 0 and value < MIN_FACES:
        raise argparse.ArgumentTypeError(f"must be 0 (keep every triangle) or at least {MIN_FACES} (max_faces), "
                                         f"got {value}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0 (metres, GiB)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a finite number above 0, got {text!r}")
    return value


def finite_float(text: str) -> float:
    """A finite number (degrees, metres that may be 0 or negative)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def device_arg(text: str) -> str:
    """`--device`: cpu, cuda or cuda:N, checked while parsing so a typo fails before any work."""
    if re.fullmatch(r"cpu|cuda(:\d+)?", text.strip()):
        return text.strip()
    raise argparse.ArgumentTypeError(f"unknown device {text!r}: use cpu, cuda or cuda:N")


def check_device(device: str) -> None:
    """`pipeline.check_device` (imports torch: call it after parsing)."""
    from hgca_core.pipeline import check_device as check

    check(device)


def check_seed_span(seed: int, count: int, what: str = "samples") -> None:
    """Refuse a seed whose last use (seed + count - 1) leaves the 64-bit range, before the first sample runs."""
    if seed + max(count, 1) - 1 > SEED_MAX:
        raise InputError(f"--seed {seed} with {count} {what} would use seeds up to {seed + count - 1}, past "
                         f"2**63 - 1; choose a seed of at most {SEED_MAX - count + 1}")


def floats_arg(what: str, positive: bool = False) -> Callable[[str], list[float]]:
    """A type for comma-separated finite numbers (`--widths 40,60`); '' gives an empty list."""
    def parse(text: str) -> list[float]:
        values = []
        for part in (p.strip() for p in text.split(",")):
            if not part:
                continue
            try:
                value = float(part)
            except ValueError:
                raise argparse.ArgumentTypeError(f"{what} must be comma-separated numbers, got {part!r} in "
                                                 f"{text!r}") from None
            if not math.isfinite(value) or (positive and value <= 0):
                raise argparse.ArgumentTypeError(f"{what} must be finite{' and above 0' if positive else ''}, "
                                                 f"got {part!r}")
            values.append(value)
        return values
    parse.__name__ = "numbers"
    return parse

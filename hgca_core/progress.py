"""Progress reporting for long work: a tqdm bar for people, JSON lines for the Blender add-on.

The JSON-lines records are a protocol between two programs that may come from different versions (the
add-on and the core's Python), so every record carries `protocol`; docs/CONTRACTS.md ("Progress records")
describes the fields. Bump PROTOCOL whenever a field changes meaning or disappears.

A reader that goes away (the add-on killed, `| head -1`, stdout closed with `>&-`) must not cost the result: the
work is expensive, so the records are dropped from then on, one warning line says so on stderr, and the command
finishes and writes its outputs as it would have (`Progress.lost`).
"""
from __future__ import annotations

import contextlib
import json
import os
import sys
import time
import warnings
from typing import Iterator, TextIO

from tqdm import tqdm

PROTOCOL = 1
PER_SAMPLE_STAGES = ("planner", "coarse", "fine", "mesh")  # run once per sample; the others once per run


class Progress:
    """`update(stage, step, total, message, sample)` from the pipeline; the mode decides how it is shown.

    `samples` is the number of completions the run makes; `sample` (0-based) names the one a record is about.
    """

    def __init__(self, mode: str = "bar", stream: TextIO | None = None, samples: int = 1) -> None:
        if mode not in ("bar", "jsonl", "none"):
            raise ValueError(f"progress mode must be bar, jsonl or none, not {mode!r}")
        self.mode = mode
        self.stream = stream if stream is not None else sys.stdout   # None: stdout was closed before we started
        self.lost = False   # the stream went away: records are dropped
        self.samples = max(1, int(samples))
        self.sample = 0  # the last sample reported: closing records ('done', 'error') carry it
        self._bar: tqdm | None = None
        self._bar_key: tuple[str, int] | None = None

    def __call__(self, stage: str, step: int, total: int, message: str = "", sample: int | None = None) -> None:
        self.update(stage, step, total, message, sample)

    def update(self, stage: str, step: int, total: int, message: str = "", sample: int | None = None) -> None:
        if sample is not None:
            self.sample = min(max(int(sample), 0), self.samples - 1)
        if self.mode == "jsonl":
            self._emit({"stage": stage, "step": step, "total": total, "message": message})
        elif self.mode == "bar":
            try:
                self._show(stage, step, total, message)
            except (OSError, ValueError):   # stderr's reader went away (`2>&1 | head`): no bar from here on
                self.mode, self._bar, self._bar_key = "none", None, None
                _silence(sys.stderr)

    def _show(self, stage: str, step: int, total: int, message: str) -> None:
        per_sample = stage in PER_SAMPLE_STAGES and self.samples > 1
        key = (stage, self.sample if per_sample else -1)
        if key != self._bar_key:
            self.close()
            desc = f"{stage} [{self.sample + 1}/{self.samples}]" if per_sample else stage
            self._bar = tqdm(total=total, desc=desc, unit="step", file=sys.stderr, leave=True)
            self._bar_key = key
        assert self._bar is not None
        self._bar.total = total
        self._bar.n = step
        if message:
            self._bar.set_postfix_str(message)
        self._bar.refresh()

    def record(self, stage: str, step: int, total: int, message: str = "", **fields) -> None:
        """A JSON-lines record with fields of its own besides the common ones (`hgca drive`'s `plan` and `tile`
        records, docs/CONTRACTS.md); nothing in the other modes, whose callers show these their own way."""
        if self.mode == "jsonl":
            self._emit({"stage": stage, "step": step, "total": total, "message": message, **fields})

    def done(self, outputs: list[str]) -> None:
        self.close()
        if self.mode == "jsonl":
            self._emit({"stage": "done", "outputs": outputs})

    def error(self, message: str) -> None:
        self.close()
        if self.mode == "jsonl":
            self._emit({"stage": "error", "message": message})

    @contextlib.contextmanager
    def failures_reported(self) -> Iterator[None]:
        """Every failure inside also ends the stream with an `error` record, then goes on up: the add-on must
        hear of each one, not only of bad input (an `InputError` by its message, anything else with its type)."""
        try:
            yield
        except Exception as exc:
            from hgca_core.errors import InputError

            self.error(str(exc) if isinstance(exc, InputError) else f"{exc.__class__.__name__}: {exc}")
            raise

    def close(self) -> None:
        if self._bar is not None:
            bar, self._bar, self._bar_key = self._bar, None, None
            try:
                bar.close()
            except (OSError, ValueError):
                self.mode = "none"
                _silence(sys.stderr)

    def _emit(self, obj: dict) -> None:
        if self.lost:
            return
        record = {"protocol": PROTOCOL, **obj, "sample": self.sample, "samples": self.samples}
        try:
            if self.stream is None:
                raise BrokenPipeError("stdout is closed")
            self.stream.write(json.dumps(record) + "\n")
            self.stream.flush()
        except (OSError, ValueError) as exc:   # a closed pipe (EPIPE), a closed file object
            self._lose(exc)

    def _lose(self, exc: BaseException) -> None:
        """Drop every later record, keep the work going, and say so once on stderr."""
        from hgca_core.errors import HgcaWarning

        self.lost = True
        if self.stream is sys.stdout and self.stream is not None:
            _silence(sys.stdout)
        why = "closed" if isinstance(exc, (BrokenPipeError, ValueError)) else f"failing ({exc})"
        try:
            warnings.warn(f"the progress stream is {why}: progress records are dropped from here on; the work "
                          "goes on and its outputs are written", HgcaWarning, stacklevel=2)
        except (OSError, ValueError):   # stderr is gone too: nothing left to tell
            pass


def _silence(stream: TextIO | None) -> None:
    """Point a standard stream's descriptor at /dev/null, so that what is still buffered (and Python's flush at
    exit) does not fail again on the closed pipe."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, stream.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):   # no descriptor (a test's StringIO): nothing to point
        pass


class StageClock:
    """A progress callback that times the stages: the seconds since the previous event (or since the clock was
    made) are charged to the stage of the event that ends them. `hgca bench` and `hgca eval` read stage times
    from the pipeline's own events this way, and each stage's event total (the coarse and fine step counts run)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.totals: dict[str, int] = {}
        self._last = time.perf_counter()

    def __call__(self, stage: str, step: int, total: int, message: str = "", sample: int = 0) -> None:
        now = time.perf_counter()
        self.totals[stage] = total
        self.seconds[stage] = self.seconds.get(stage, 0.0) + (now - self._last)
        self._last = now

    def total(self, *stages: str) -> float:
        """Seconds charged to the named stages (all of them when none is named)."""
        return sum(v for k, v in self.seconds.items() if not stages or k in stages)

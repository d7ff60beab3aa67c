"""Progress reporting for long work: a tqdm bar for people, JSON lines for the Blender add-on."""
from __future__ import annotations

import json
import sys
import time
from typing import TextIO

from tqdm import tqdm


class Progress:
    """`update(stage, step, total, message)` from the pipeline; the mode decides how it is shown."""

    def __init__(self, mode: str = "bar", stream: TextIO | None = None) -> None:
        if mode not in ("bar", "jsonl", "none"):
            raise ValueError(f"progress mode must be bar, jsonl or none, not {mode!r}")
        self.mode = mode
        self.stream = stream or sys.stdout
        self._bar: tqdm | None = None
        self._stage: str | None = None

    def __call__(self, stage: str, step: int, total: int, message: str = "") -> None:
        self.update(stage, step, total, message)

    def update(self, stage: str, step: int, total: int, message: str = "") -> None:
        if self.mode == "jsonl":
            self._emit({"stage": stage, "step": step, "total": total, "message": message})
        elif self.mode == "bar":
            if stage != self._stage:
                self.close()
                self._bar = tqdm(total=total, desc=stage, unit="step", file=sys.stderr, leave=True)
                self._stage = stage
            assert self._bar is not None
            self._bar.total = total
            self._bar.n = step
            if message:
                self._bar.set_postfix_str(message)
            self._bar.refresh()

    def done(self, outputs: list[str]) -> None:
        self.close()
        if self.mode == "jsonl":
            self._emit({"stage": "done", "outputs": outputs})

    def error(self, message: str) -> None:
        self.close()
        if self.mode == "jsonl":
            self._emit({"stage": "error", "message": message})

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
            self._stage = None

    def _emit(self, obj: dict) -> None:
        self.stream.write(json.dumps(obj) + "\n")
        self.stream.flush()


class StageClock:
    """A progress callback that times the stages: the seconds since the previous event (or since the clock was
    made) are charged to the stage of the event that ends them. `hgca bench` and `hgca eval` read stage times
    from the pipeline's own events this way."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._last = time.perf_counter()

    def __call__(self, stage: str, step: int, total: int, message: str = "") -> None:
        now = time.perf_counter()
        self.seconds[stage] = self.seconds.get(stage, 0.0) + (now - self._last)
        self._last = now

    def total(self, *stages: str) -> float:
        """Seconds charged to the named stages (all of them when none is named)."""
        return sum(v for k, v in self.seconds.items() if not stages or k in stages)

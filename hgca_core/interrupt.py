"""Ctrl-C (SIGINT) and SIGTERM in the `hgca` command: stop at once, one line, exit 130 / 143, no partial output.

Python's default turns SIGINT into `KeyboardInterrupt`, which any `except BaseException` on the way swallows
(trimesh wraps its optional imports that way: a Ctrl-C while it imported was lost and the run went on), and
leaves SIGTERM to kill the process without a word. The handler here does not raise: it removes the temp
files of writes in progress (`hgca_core.io.atomic`), prints one line and ends the process with `os._exit`.
A signal that lands while finished outputs are being moved into place waits for that (milliseconds), so a
run leaves all its outputs or none. Only the CLI installs it; `hgca_core` as a library keeps Python's default.

This module imports nothing heavy: the CLI installs it before importing anything else.
"""
from __future__ import annotations

import contextlib
import os
import signal
import sys
from typing import Any, Callable, Iterator

EXIT_CODES = {signal.SIGINT: 130, signal.SIGTERM: 143}
_COMMAND = {"name": ""}
_LAST_WORDS: list[Callable[[int], None]] = []   # see `last_words`


@contextlib.contextmanager
def last_words(fn: Callable[[int], None]) -> Iterator[None]:
    """While the block runs, `fn(signum)` is called when the handler ends the process (after the temp files are
    gone, before the exit): `hgca drive` marks its drive.json interrupted there, so a folder a signal stopped
    does not read as still running. `fn` must be quick and must not raise (what it raises is ignored)."""
    _LAST_WORDS.append(fn)
    try:
        yield
    finally:
        _LAST_WORDS.remove(fn)


def _handler(signum: int, _frame: Any) -> None:
    atomic = sys.modules.get("hgca_core.io.atomic")  # not imported yet: nothing can be half-written
    if atomic is not None and atomic.defer_signal(signum):
        return
    if atomic is not None:
        atomic.discard_pending()
    for fn in reversed(_LAST_WORDS):
        try:
            fn(signum)
        except BaseException:  # noqa: BLE001  (the process ends either way; its outputs must not)
            pass
    what = "interrupted" if signum == signal.SIGINT else "terminated"
    name = f"hgca {_COMMAND['name']}".strip()
    try:
        sys.stdout.flush()
    except (OSError, ValueError):
        pass
    try:
        lead = "\n" if sys.stderr.isatty() else ""  # end a progress bar's line first
        sys.stderr.write(f"{lead}{name}: {what} ({signal.Signals(signum).name})\n")
        sys.stderr.flush()
    except (OSError, ValueError):
        pass
    os._exit(EXIT_CODES.get(signum, 128 + signum))


def install(command: str = "") -> dict[int, Any]:
    """Handle SIGINT and SIGTERM as above; returns the previous handlers for `restore`.

    A SIGINT that was ignored when the process started (`nohup`, a background job of a script) stays ignored,
    as Python itself does it."""
    _COMMAND["name"] = command
    previous = {}
    for sig in EXIT_CODES:
        current = signal.getsignal(sig)
        if sig == signal.SIGINT and current == signal.SIG_IGN:
            continue
        previous[sig] = current
        signal.signal(sig, _handler)
    return previous


def installed() -> bool:
    """Whether this process's SIGTERM is handled here (the CLI), so long calls should stay interruptible."""
    return signal.getsignal(signal.SIGTERM) is _handler


def restore(previous: dict[int, Any]) -> None:
    for sig, handler in previous.items():
        if handler is not None:
            signal.signal(sig, handler)

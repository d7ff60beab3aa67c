"""One error type for bad input, so callers (CLI, Blender) can show a clear message instead of a traceback."""
from __future__ import annotations


class HgcaError(Exception):
    """Base class of every error hgca raises on purpose."""


class InputError(HgcaError, ValueError):
    """Bad user input: unreadable, empty, corrupt or non-finite scans, empty regions, oversize regions.

    The message always names the file (when there is one) and what is wrong with it.
    """

    def __init__(self, message: str, path: str | None = None) -> None:
        self.path = path
        super().__init__(f"{path}: {message}" if path else message)


class HgcaWarning(UserWarning):
    """Something worth knowing that does not stop the run (the CLI prints it as one `warning:` line)."""

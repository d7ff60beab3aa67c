"""The core's settings as the add-on knows them: defaults, bounds, choices and CLI flags, from the schema the
extension build writes beside this file (`core_settings.json`, `hgca_core.config.addon_schema()`).

The add-on never imports hgca_core (it runs it as a child process), so the panel's properties and every job's
command line are made from this one record instead of copies of the core's numbers: a bound changed in the core
reaches the panel with the next build. A checkout loaded without a build reads the schema from the core beside it.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

SCHEMA_FILE = Path(__file__).resolve().parent / "core_settings.json"


def _load() -> dict[str, Any]:
    if SCHEMA_FILE.is_file():
        return json.loads(SCHEMA_FILE.read_text())
    checkout = SCHEMA_FILE.parents[1]             # hgca_blender/ in a clone: hgca_core/ is its sibling
    if (checkout / "hgca_core" / "config.py").is_file():
        if str(checkout) not in sys.path:
            sys.path.append(str(checkout))
        from hgca_core.config import addon_schema  # torch-free

        return addon_schema()
    raise RuntimeError(f"{SCHEMA_FILE.name} is missing beside the add-on: rebuild the extension (make extension)")


SCHEMA = _load()
LIMITS: dict[str, dict[str, Any]] = SCHEMA["settings"]
FLAGS: dict[str, str] = SCHEMA["flags"]
HELP: dict[str, str] = SCHEMA.get("help", {})
REGION_SIZE: tuple[float, float, float] = tuple(SCHEMA["region_size"])   # the core's default region (metres)
INT_MAX = 2**31 - 1   # Blender's IntProperty holds 32-bit values


def default(name: str) -> Any:
    return LIMITS[name]["default"]


def low(name: str, fallback: float = 0) -> Any:
    value = LIMITS[name].get("min")
    return fallback if value is None else value


def high(name: str, fallback: float = INT_MAX) -> Any:
    value = LIMITS[name].get("max")
    return fallback if value is None else min(value, fallback)


def choices(name: str) -> list[str]:
    return list(LIMITS[name]["choices"])


def check(name: str, value: Any) -> None:
    """ValueError naming the setting when `value` lies outside the core's bounds or choices (before a job starts)."""
    spec = LIMITS[name]
    if "choices" in spec and value not in spec["choices"]:
        raise ValueError(f"{name} must be one of {', '.join(spec['choices'])}, got {value!r}")
    if spec.get("min") is not None and value < spec["min"] or spec.get("max") is not None and value > spec["max"]:
        raise ValueError(f"{name} must lie between {spec.get('min')} and {spec.get('max')}, got {value!r}")


def checked(name: str, value: Any) -> None:
    """`check`, except that a face limit of 0 passes: it keeps every triangle (the core's default is a limit)."""
    if not (name == "max_faces" and int(value) == 0):
        check(name, value)


def parse_type(name: str):
    """An argparse type for setting `name` (the batch's options): the default's type, checked against the core's
    bounds and choices; 0 stays allowed where it means "the core decides" (steps from the weights, every face)."""
    import argparse

    kind = type(default(name))

    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a {kind.__name__}: {text!r}") from None
        try:
            checked(name, value)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
        return value
    parse.__name__ = name
    return parse


def core_args(values: dict[str, Any]) -> list[str]:
    """The one settings -> argv of every job: each setting as the core's flag and value, in the schema's order;
    step counts of 0 (the weights' own) and a face limit of 0 are left to the core."""
    args: list[str] = []
    for name, flag in FLAGS.items():
        if name not in values:
            continue
        value = values[name]
        if name in ("t1", "t2") and not int(value):
            continue
        checked(name, value)
        args += [flag, repr(float(value)) if isinstance(value, float) else str(value)]
    return args

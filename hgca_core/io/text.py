"""XYZ / CSV / TXT point tables: comma, semicolon or whitespace separated, optional header line.

With a header, the coordinates are the columns it names x, y, z (any case) or easting, northing, elevation
(`AXIS_NAMES`), wherever they stand; the other named columns become attributes. A header that names no
coordinates, or only some, is refused: reading such a table by position would put `id` or `z` into x without
a word. Without a header the first three columns are x, y, z and the rest become `column_3`, `column_4`, ...
A comment line just above the data that names every column (`# z y x`, CloudCompare's `//X,Y,Z`) is a header.
A UTF-8 byte-order mark is skipped; numbers Python does not read as decimals (hex floats, decimal commas) are
refused by name rather than taken for a header.
"""
from __future__ import annotations

import re
import warnings

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.scan import Scan

_HEX = re.compile(r"^[+-]?0x[0-9a-f]*\.?[0-9a-f]*(p[+-]?\d+)?$", re.IGNORECASE)
_DECIMAL_COMMA = re.compile(r"^[+-]?\d+,\d+$")
_UNIT = re.compile(r"\s*[\[(][^\])]*[\])]$")   # "x [m]", "Easting (m)"
AXIS_NAMES: dict[str, tuple[str, ...]] = {
    "x": ("x", "easting", "east"),
    "y": ("y", "northing", "north"),
    "z": ("z", "elevation", "height", "altitude", "elev", "alt"),
}
_DEGREES = ("lat", "lon", "long", "latitude", "longitude")


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _clean(name: str) -> str:
    """A header name without quotes, comment marks and a unit suffix."""
    return _UNIT.sub("", name.strip().strip('"').strip("'").lstrip("/#").strip())


def _not_decimal(tokens: list[str]) -> str | None:
    """Why tokens that look like numbers are not numbers hgca reads, or None."""
    for t in tokens:
        if _HEX.match(t):
            return f"hexadecimal number {t!r}: write decimal numbers (e.g. {float.fromhex(t)!r})" \
                if _hex_value(t) is not None else f"hexadecimal number {t!r}: write decimal numbers"
        if _DECIMAL_COMMA.match(t):
            return f"decimal comma in {t!r}: write decimal points (1.5, not 1,5)"
    return None


def _hex_value(token: str) -> float | None:
    try:
        return float.fromhex(token)
    except ValueError:
        return None


def _split(line: str, delimiter: str | None) -> list[str]:
    parts = line.split(delimiter) if delimiter else line.split()
    return [p.strip() for p in parts]


def _head(path: str) -> tuple[str | None, str | None, int]:
    """The first data-or-header line, the last comment line above it, and the number of lines up to it."""
    with open(path, "rb") as f:
        start = f.read(4)
    if start.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise InputError("text is UTF-16 (it starts with a UTF-16 byte-order mark): save it as UTF-8 or ASCII", path)
    first, comment, skip = None, None, 0
    with open(path, "r", encoding="utf-8-sig", errors="replace") as f:
        for line in f:
            skip += 1
            text = line.strip()
            if not text:
                continue
            if text.startswith("#"):
                comment = text
                continue
            first = text
            break
    return first, comment, skip


def _axes(names: list[str], path: str) -> list[int]:
    """The columns of x, y, z named in a header, or InputError when it names none, some, or one twice."""
    lower = [_clean(n).lower() for n in names]
    dupes = sorted({n for n in lower if n and lower.count(n) > 1})
    if dupes:
        raise InputError(f"header names column {dupes[0]!r} {lower.count(dupes[0])} times "
                         f"(header: {', '.join(names)})", path)
    found: dict[str, list[int]] = {a: [i for i, n in enumerate(lower) if n in AXIS_NAMES[a]] for a in AXIS_NAMES}
    for axis, cols in found.items():
        if len(cols) > 1:
            raise InputError(f"header names {axis} twice ({', '.join(names[i] for i in cols)})", path)
    missing = [a for a, cols in found.items() if not cols]
    if missing:
        degrees = [n for n in names if _clean(n).lower() in _DEGREES]
        hint = (f"; {', '.join(degrees)} are degrees: project them to metres (e.g. UTM) first" if degrees else
                "; name the columns x, y, z (or easting, northing, elevation), or drop the header to read the "
                "first three columns as x, y, z")
        raise InputError(f"header ({', '.join(names)}) names no {' or '.join(missing)} column{hint}", path)
    return [found[a][0] for a in ("x", "y", "z")]


def _comment_header(comment: str | None, delimiter: str | None, ncols: int) -> list[str] | None:
    """A comment line above the data that names every column and all of x, y, z (`# z y x`), else None."""
    if comment is None:
        return None
    tokens = [t for t in _split(comment.lstrip("#").strip(), delimiter) if t]
    if len(tokens) != ncols or any(_is_number(t) for t in tokens):
        return None
    lower = [_clean(t).lower() for t in tokens]
    if all(any(n in AXIS_NAMES[a] for n in lower) for a in AXIS_NAMES) and len(set(lower)) == len(lower):
        return tokens
    return None


def _load(path: str, delimiter: str | None, skip: int) -> np.ndarray:
    try:
        with warnings.catch_warnings():  # "input contained no data" is reported by the caller as InputError
            warnings.simplefilter("ignore", UserWarning)
            with open(path, "r", encoding="utf-8-sig", errors="replace") as f:
                return np.loadtxt(f, dtype=np.float64, delimiter=delimiter, comments="#", skiprows=skip, ndmin=2,
                                  quotechar='"')
    except ValueError as exc:
        reason = str(exc).split(";")[0]  # drop numpy's `usecols` advice, which is no use to a CLI user
        bad = re.search(r"could not convert string '([^']*)'", reason)
        why = _not_decimal([bad.group(1)]) if bad else None
        if bad and not bad.group(1).strip():
            why = "an empty value: a doubled delimiter, or one at the end of the rows"
        raise InputError(f"malformed text table ({reason}){': ' + why if why else ''}", path) from None


def read_xyz(path: str) -> Scan:
    """Read a numeric table; the delimiter and header are detected from the first non-comment line."""
    first, comment, skip = _head(path)
    if first is None:
        raise InputError("contains no points (only blank or comment lines)", path)
    delimiter = ";" if ";" in first else ("," if "," in first else None)
    if delimiter == "," and len(first.split()) >= 3 and all(_DECIMAL_COMMA.match(t) for t in first.split()):
        delimiter = None                    # "1,5 2,5 3,5": whitespace columns of decimal-comma numbers
    tokens = [t for t in _split(first, delimiter) if t]
    unquoted = [t.strip('"').strip("'") for t in tokens]
    why = _not_decimal(unquoted)
    if why is not None:
        raise InputError(f"line {skip} holds a {why}", path)
    numeric = [_is_number(t) for t in unquoted]
    header = None
    if not all(numeric):
        if any(numeric):
            raise InputError(f"line {skip} mixes numbers and names ({', '.join(tokens)}): neither a header nor a "
                             "data row", path)
        header = [_clean(t) or t for t in tokens]
    table = _load(path, delimiter, skip if header else 0)
    if table.size == 0:
        raise InputError("contains no points (no data rows)", path)
    ncols = table.shape[1]
    if ncols < 3:
        raise InputError(f"needs at least 3 columns (x, y, z), found {ncols}", path)
    if header is not None and len(header) != ncols:
        raise InputError(f"header names {len(header)} columns but rows have {ncols}", path)
    if header is None:
        header = _comment_header(comment, delimiter, ncols)
    if header is None:
        names = ["x", "y", "z", *[f"column_{i}" for i in range(3, ncols)]]
        xyz = [0, 1, 2]
    else:
        names = header
        xyz = _axes(header, path)
    points = table[:, xyz]
    attributes = {names[i]: table[:, i].copy() for i in range(ncols) if i not in xyz}
    return Scan(points, attributes, None, path)

"""XYZ / CSV / TXT point tables: comma, semicolon or whitespace separated, optional header line.

With a header, columns named x, y, z (any case) are the coordinates and the other named columns become
attributes; without one, the first three columns are x, y, z and the rest become `column_3`, `column_4`, ...
"""
from __future__ import annotations

import re
import warnings

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.scan import Scan

_SPLIT = re.compile(r"[,;\s]+")


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def read_xyz(path: str) -> Scan:
    """Read a numeric table; the delimiter and header are detected from the first non-comment line."""
    with open(path, "r", encoding="utf-8", errors="replace") as f:
        first, skip = None, 0
        for line in f:
            skip += 1
            if line.strip() and not line.lstrip().startswith("#"):
                first = line.strip()
                break
    if first is None:
        raise InputError("contains no points (only blank or comment lines)", path)
    delimiter = "," if "," in first else (";" if ";" in first else None)
    tokens = [t for t in _SPLIT.split(first) if t]
    header = None if all(_is_number(t) for t in tokens) else [t.strip().strip('"').strip("'") for t in tokens]
    try:
        with warnings.catch_warnings():  # "input contained no data" is reported below as InputError
            warnings.simplefilter("ignore", UserWarning)
            table = np.loadtxt(path, dtype=np.float64, delimiter=delimiter, comments="#",
                               skiprows=skip if header else 0, ndmin=2)
    except ValueError as exc:
        reason = str(exc).split(";")[0]  # drop numpy's `usecols` advice, which is no use to a CLI user
        raise InputError(f"malformed text table ({reason})", path) from None
    if table.size == 0:
        raise InputError("contains no points (no data rows)", path)
    ncols = table.shape[1]
    if ncols < 3:
        raise InputError(f"needs at least 3 columns (x, y, z), found {ncols}", path)
    if header is not None and len(header) != ncols:
        raise InputError(f"header names {len(header)} columns but rows have {ncols}", path)
    names = header if header is not None else ["x", "y", "z", *[f"column_{i}" for i in range(3, ncols)]]
    lower = [n.lower() for n in names]
    xyz = [lower.index(c) if c in lower else None for c in ("x", "y", "z")]
    if None in xyz:
        xyz = [0, 1, 2]
    points = table[:, xyz]
    attributes = {names[i]: table[:, i].copy() for i in range(ncols) if i not in xyz}
    return Scan(points, attributes, None, path)

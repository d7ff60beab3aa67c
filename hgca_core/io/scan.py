"""The `Scan` container every reader returns, and the one place that enforces the coordinate policy (finite,
on Earth, in one float32 frame: `hgca_core.io.georef`).

Keeping the policy here (not in each reader) means every format drops sensor "no return" rows and rejects
other non-finite coordinates in exactly the same way.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hgca_core.errors import InputError
from hgca_core.io.georef import check_bound, check_coordinates


@dataclass
class Scan:
    """Points in world metres with per-point attributes and the sensor origins they were seen from.

    `origins` is None when the file does not say where the sensor was (aerial LAS, plain XYZ); the
    pipeline then estimates what it needs from the points alone. `dropped` counts rows of the file a reader
    left out on purpose, by reason (e.g. nuScenes returns off the own car), so that `hgca info` can say so.
    """

    points: np.ndarray
    attributes: dict[str, np.ndarray] = field(default_factory=dict)
    origins: np.ndarray | None = None
    path: str | None = None
    dropped: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.points = np.ascontiguousarray(self.points, dtype=np.float64)
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise ValueError(f"Scan.points must be (N, 3), got {self.points.shape}")
        n = len(self.points)
        self.attributes = {str(k): np.asarray(v) for k, v in self.attributes.items()}
        for name, values in self.attributes.items():
            if values.shape != (n,):
                raise ValueError(f"Scan attribute {name!r} must be ({n},), got {values.shape}")
        if self.origins is not None:
            self.origins = np.ascontiguousarray(self.origins, dtype=np.float64).reshape(-1, 3)

    def __len__(self) -> int:
        return len(self.points)


def finalize(scan: Scan, path: str | None = None) -> Scan:
    """Apply the finite policy: drop all-NaN rows (organized clouds' no-return placeholders), reject the rest.

    Any other NaN/inf coordinate means a corrupt or mis-parsed file, and a scan with nothing left cannot be
    completed, so both raise `InputError` naming the file.
    """
    where = path if path is not None else scan.path
    pts = scan.points
    if len(pts) == 0:
        raise InputError("contains no points", where)
    finite = np.isfinite(pts)
    if not finite.all():
        placeholder = np.isnan(pts).all(axis=1)
        bad = ~finite.all(axis=1) & ~placeholder
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            raise InputError(
                f"{int(bad.sum())} point(s) have NaN or infinite coordinates "
                f"(first at row {first}: {pts[first].tolist()})",
                where,
            )
        keep = ~placeholder
        if not keep.any():
            raise InputError(f"contains no points: all {len(pts)} rows are no-return (NaN) placeholders", where)
        scan = Scan(
            points=pts[keep],
            attributes={k: v[keep] for k, v in scan.attributes.items()},
            origins=scan.origins,
            path=scan.path,
            dropped=scan.dropped,
        )
    check_coordinates(scan.points, where)
    if scan.origins is not None:
        if not np.isfinite(scan.origins).all():
            raise InputError("sensor origin has NaN or infinite values", where)
        check_bound(scan.origins, where, "sensor origin")
        index = scan.attributes.get("origin_index")
        if index is not None and len(index) and (index.min() < 0 or index.max() >= len(scan.origins)):
            raise InputError(f"origin_index runs from {index.min()} to {index.max()} but there are "
                             f"{len(scan.origins)} sensor origin(s)", where)
    return scan

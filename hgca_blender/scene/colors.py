"""Point colours for imported scans: RGB when the file has it, else intensity or height, as a colour attribute.

A colour attribute (not a material) is what Blender's Solid view draws when its colour is set to *Attribute*,
and the Geometry Nodes points carry it along, so the scan reads the same in Solid view, Material Preview and
renders. Values are scaled robustly (percentiles), so one bright return or one stray point does not wash the
rest out.
"""
from __future__ import annotations

import numpy as np

COLOR_ATTRIBUTE = "hgca_color"
MODES = ("AUTO", "RGB", "INTENSITY", "HEIGHT", "NONE")
# a perceptually ordered ramp (viridis at 0, 0.25, 0.5, 0.75, 1) for scalar fields
RAMP = np.array([[0.267, 0.005, 0.329], [0.229, 0.322, 0.546], [0.128, 0.567, 0.551],
                 [0.369, 0.789, 0.383], [0.993, 0.906, 0.144]], dtype=np.float32)
RGB_NAMES = (("red", "green", "blue"), ("r", "g", "b"))
# the darkest intensity grey (linear): the weakest returns stay visible on Blender's dark viewport background
INTENSITY_FLOOR = 0.12


def rgb_of(attributes: dict[str, np.ndarray]) -> np.ndarray | None:
    """(N, 3) float 0..1 from red/green/blue attributes (8-bit or LAS's 16-bit), or None when there are none."""
    for names in RGB_NAMES:
        if all(n in attributes for n in names):
            rgb = np.stack([np.asarray(attributes[n], dtype=np.float64) for n in names], axis=1)
            top = float(np.nanmax(rgb)) if rgb.size else 0.0
            scale = 65535.0 if top > 255 else 255.0 if top > 1 else 1.0
            return np.clip(rgb / scale, 0.0, 1.0).astype(np.float32)
    return None


def normalised(values: np.ndarray, lo_pct: float = 1.0, hi_pct: float = 99.0) -> np.ndarray:
    """Values mapped to 0..1 between two percentiles (a constant field maps to 0.5)."""
    v = np.asarray(values, dtype=np.float64)
    finite = v[np.isfinite(v)]
    if not len(finite):
        return np.full(len(v), 0.5, dtype=np.float32)
    lo, hi = np.percentile(finite, [lo_pct, hi_pct])
    if hi <= lo:
        return np.full(len(v), 0.5, dtype=np.float32)
    return np.clip((np.nan_to_num(v, nan=lo) - lo) / (hi - lo), 0.0, 1.0).astype(np.float32)


def equalised(values: np.ndarray) -> np.ndarray:
    """Each value's share of the finite values at or below it (0..1): LiDAR intensities are heavy-tailed (most
    returns weak, a few retro-reflectors strong), so a linear scale leaves nearly every point black; ranks
    spread them evenly. NaN maps to 0."""
    v = np.asarray(values, dtype=np.float64)
    finite = np.sort(v[np.isfinite(v)])
    if not len(finite) or finite[0] == finite[-1]:
        return np.full(len(v), 0.5, dtype=np.float32)
    ranks = np.searchsorted(finite, np.nan_to_num(v, nan=-np.inf), side="right") / len(finite)
    return ranks.astype(np.float32)


def ramp(t: np.ndarray, stops: np.ndarray = RAMP) -> np.ndarray:
    """(N, 3) colours of `t` in 0..1 along `stops` (linear between them)."""
    x = np.clip(np.asarray(t, dtype=np.float64), 0.0, 1.0) * (len(stops) - 1)
    i = np.minimum(x.astype(np.int64), len(stops) - 2)
    f = (x - i)[:, None]
    return (stops[i] * (1 - f) + stops[i + 1] * f).astype(np.float32)


def point_colors(mode: str, points: np.ndarray, attributes: dict[str, np.ndarray]) -> tuple[np.ndarray | None, str]:
    """(N, 4) RGBA colours for `mode` and the mode used (AUTO: RGB, else intensity, else height), or
    (None, "NONE"). A mode the data cannot give (RGB of a scan without colours) raises ValueError."""
    if mode == "NONE":
        return None, "NONE"
    rgb = rgb_of(attributes)
    if mode == "AUTO":
        mode = "RGB" if rgb is not None else "INTENSITY" if "intensity" in attributes else "HEIGHT"
    if mode == "RGB":
        if rgb is None:
            raise ValueError("this scan has no RGB colours (red, green, blue): colour it by intensity or height")
        colors = rgb
    elif mode == "INTENSITY":
        if "intensity" not in attributes:
            raise ValueError("this scan has no intensity: colour it by height")
        grey = INTENSITY_FLOOR + (1.0 - INTENSITY_FLOOR) * equalised(attributes["intensity"])
        colors = np.repeat(grey[:, None].astype(np.float32), 3, axis=1)
    elif mode == "HEIGHT":
        colors = ramp(normalised(np.asarray(points)[:, 2], 2.0, 98.0))
    else:
        raise ValueError(f"unknown colour mode {mode!r}: one of {', '.join(MODES)}")
    rgba = np.ones((len(colors), 4), dtype=np.float32)
    rgba[:, :3] = colors
    return rgba, mode


def default_point_radius(points: np.ndarray, has_sensor: bool) -> float:
    """A point radius that reads well: 3 cm for scans from a vehicle (dense near the sensor); for aerial and
    other scans without a sensor position, half the mean spacing over the x/y extent (within 2 cm .. 2 m)."""
    pts = np.asarray(points, dtype=np.float64)
    if has_sensor or len(pts) < 2:
        return 0.03
    extent = pts[:, :2].max(axis=0) - pts[:, :2].min(axis=0)
    area = float(max(extent[0], 1e-3) * max(extent[1], 1e-3))
    return float(np.clip(0.5 * np.sqrt(area / len(pts)), 0.02, 2.0))

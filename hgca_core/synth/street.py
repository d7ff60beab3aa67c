"""The street layout's numbers (`Street`) and how a place in street coordinates lands in the world: what the
scene and the blocks of buildings beside it both build on (street coordinates: u along the main street's centre
line, v across it)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hgca_core.synth.terrain import StreetCurve, Terrain, tilt_to

EXTENT = 60.0       # half size of the layout square in street coordinates (metres)


@dataclass
class Street:
    """The layout's numbers and how a place in street coordinates lands in the world."""

    hw: float              # road half width (curb to centre line)
    sw: float              # sidewalk width
    hs: float              # sidewalk (curb) height
    cross: bool            # has a cross street
    xc: float              # where the cross street's centre line meets the main one (u)
    hw2: float             # cross street half width
    theta: float           # angle between the streets (radians, in street coordinates)
    curve: StreetCurve
    terrain: Terrain

    def cross_u(self, v: float) -> float:
        """u of the cross street's centre line at lateral position v."""
        return self.xc + v / np.tan(self.theta)

    def cross_span(self, v0: float, v1: float, margin: float, width: float | None = None) -> tuple[float, float]:
        """u interval the cross street (carriageway + sidewalks, or `width` either side) covers for v in [v0, v1]."""
        half = ((self.hw2 + self.sw) if width is None else width) / np.sin(self.theta) + margin
        us = [self.cross_u(v0), self.cross_u(v1)]
        return min(us) - half, max(us) + half

    def x_free(self, u: float, margin: float, v0: float | None = None, v1: float | None = None) -> bool:
        """Whether u is clear of the cross street by `margin` between lateral positions v0 and v1 (default:
        across the main street's sidewalks)."""
        if not self.cross:
            return True
        v0 = -(self.hw + self.sw) if v0 is None else v0
        v1 = self.hw + self.sw if v1 is None else v1
        lo, hi = self.cross_span(v0, v1, margin)
        return not lo < u < hi

    def place(self, u: float, v: float, yaw: float = 0.0, foot=(-0.3, -0.3, 0.3, 0.3), lift: float = 0.0,
              tilt: bool = False) -> tuple[float, np.ndarray, np.ndarray | None]:
        """Arguments for `MeshBuilder.placed`: an object at street coordinates (u, v), turned by `yaw` from
        the street direction, standing on the lowest ground under its footprint (x0, y0, x1, y1 in its own
        frame) plus `lift`. With `tilt` (vehicles) it is set onto the plane through the ground under the
        footprint's corners, raised until no corner is below the ground."""
        xy = self.curve.to_world(u, v)
        yaw_w = float(self.curve.heading(u)) + yaw
        x0, y0, x1, y1 = foot
        c, s = np.cos(yaw_w), np.sin(yaw_w)
        local = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [(x0 + x1) / 2, (y0 + y1) / 2]])
        corners = xy + local @ np.array([[c, s], [-s, c]])
        z = self.terrain.height(corners)
        if not tilt:
            return yaw_w, np.r_[xy, z.min() + lift], None
        a = np.c_[corners - xy, np.ones(5)]
        gx, gy, z0 = np.linalg.lstsq(a, z, rcond=None)[0]
        z0 += max(0.0, float(np.max(z - a @ [gx, gy, z0])))
        return yaw_w, np.r_[xy, z0 + lift], tilt_to([-gx, -gy, 1.0])

    def side(self, s: int, u: float, v: float, yaw: float = 0.0, foot=(-0.3, -0.3, 0.3, 0.3), lift: float = 0.0,
             tilt: bool = False):
        """`place` for an object whose local -y faces the main street, on side s (+1 north, -1 south); its local
        x runs along +u on the north side and along -u on the south side."""
        return self.place(u, s * v, yaw + (0.0 if s > 0 else np.pi), foot, lift, tilt)

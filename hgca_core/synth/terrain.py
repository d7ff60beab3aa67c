"""Ground that is not flat, and a main street that may bend.

`Terrain` is a height grid triangulated exactly like the ground mesh, so "below the ground" means below
the surface the LiDAR sees. `StreetCurve` maps street coordinates (u along the main street, v across it,
+v to the left of +u) to the world: the layout is written in (u, v) as if the street were straight and
bends with the centre line y = k x^2 / 2.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class Terrain:
    """Heights on a regular grid over [x0, x0 + step (nx - 1)] x [y0, y0 + step (ny - 1)]; each cell is two
    triangles split along its (i, j) -> (i + 1, j + 1) diagonal, as in `mesh_arrays`."""

    def __init__(self, x0: float, y0: float, step: float, heights: np.ndarray) -> None:
        self.x0, self.y0, self.step = float(x0), float(y0), float(step)
        self.heights = np.asarray(heights, dtype=np.float64)

    @classmethod
    def flat(cls, half: float, z: float = 0.0) -> "Terrain":
        return cls(-half, -half, 2 * half, np.full((2, 2), z))

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Ground height under each (x, y) (clamped to the grid's edge outside it)."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        nx, ny = self.heights.shape
        fx = np.clip((p[:, 0] - self.x0) / self.step, 0.0, nx - 1 - 1e-9)
        fy = np.clip((p[:, 1] - self.y0) / self.step, 0.0, ny - 1 - 1e-9)
        i, j = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
        tx, ty = fx - i, fy - j
        h = self.heights
        ha, hb, hc, hd = h[i, j], h[i + 1, j], h[i + 1, j + 1], h[i, j + 1]
        lower = tx >= ty                                            # triangle (a, b, c), else (a, c, d)
        return np.where(lower, ha + tx * (hb - ha) + ty * (hc - hb), ha + ty * (hd - ha) + tx * (hc - hd))

    def up(self, xy: np.ndarray, span: float = 1.5) -> np.ndarray:
        """Unit normals of the ground averaged over +-span metres (what a car's wheels rest on)."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        dx = (self.height(p + [span, 0]) - self.height(p - [span, 0])) / (2 * span)
        dy = (self.height(p + [0, span]) - self.height(p - [0, span])) / (2 * span)
        n = np.stack([-dx, -dy, np.ones_like(dx)], axis=1)
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def mesh_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(vertices, faces) of the ground surface, upward facing."""
        nx, ny = self.heights.shape
        gx, gy = np.meshgrid(self.x0 + self.step * np.arange(nx), self.y0 + self.step * np.arange(ny), indexing="ij")
        v = np.c_[gx.ravel(), gy.ravel(), self.heights.ravel()]
        ii, jj = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), indexing="ij")
        a = (ii * ny + jj).ravel()
        b, c, d = a + ny, a + ny + 1, a + 1
        return v, np.vstack([np.c_[a, b, c], np.c_[a, c, d]])


def tilt_to(up: np.ndarray) -> np.ndarray:
    """The 3x3 rotation that turns +z onto the unit vector `up` (the smallest turn)."""
    u = np.asarray(up, dtype=np.float64).reshape(3)
    u = u / np.linalg.norm(u)
    axis = np.cross([0.0, 0.0, 1.0], u)
    s, c = np.linalg.norm(axis), u[2]
    if s < 1e-12:
        return np.eye(3)
    k = axis / s
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * kx + (1 - c) * kx @ kx


@dataclass(frozen=True)
class StreetCurve:
    """Centre line y = k x^2 / 2 of the main street (k = 0: straight)."""

    k: float = 0.0

    def slope(self, u: np.ndarray) -> np.ndarray:
        return self.k * np.asarray(u, dtype=np.float64)

    def heading(self, u) -> np.ndarray:
        """World yaw of the street direction +u at u."""
        return np.arctan(self.slope(u))

    def to_world(self, u, v) -> np.ndarray:
        """(..., 2) world x, y of street coordinates u, v (the centre line point moved v along the normal)."""
        u, v = np.broadcast_arrays(np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64))
        c1 = self.slope(u)
        norm = np.sqrt(1.0 + c1 * c1)
        return np.stack([u - v * c1 / norm, 0.5 * self.k * u * u + v / norm], axis=-1)

    def to_street(self, xy: np.ndarray, iterations: int = 8) -> np.ndarray:
        """(N, 2) street coordinates (u, v) of world points: Newton's method on the foot point u, where
        (p - C(u)) . C'(u) = 0 for the centre line C(u) = (u, k u^2 / 2)."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        u = p[:, 0].copy()
        for _ in range(iterations):
            c1 = self.slope(u)
            d = p - np.stack([u, 0.5 * self.k * u * u], axis=1)
            f = d[:, 0] + c1 * d[:, 1]
            u = u - f / (-(1.0 + c1 * c1) + d[:, 1] * self.k)
        c1 = self.slope(u)
        d = p - np.stack([u, 0.5 * self.k * u * u], axis=1)
        v = (-c1 * d[:, 0] + d[:, 1]) / np.sqrt(1.0 + c1 * c1)
        return np.stack([u, v], axis=1)


def make_terrain(rng: np.random.Generator, half: float, curve: StreetCurve, road_half_width: float,
                 step: float = 2.0) -> tuple[Terrain, dict]:
    """Ground of a scene: flat, a steady grade, or rolling hills (with a grade), a cambered main road and a
    few centimetres of unevenness off the road. Returns the terrain and what was drawn (for the layout)."""
    kind = str(rng.choice(["flat", "grade", "hills"], p=[0.25, 0.35, 0.4]))
    n = int(np.ceil(2 * half / step)) + 1
    xs = -half + step * np.arange(n)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    h = np.zeros_like(gx)
    info: dict = {"kind": kind}
    if kind != "flat":
        grade = rng.uniform(0.02, 0.08) * rng.choice([-1, 1])      # along the street
        cross = rng.normal(0.0, 0.015)                             # across it
        h += grade * gx + cross * gy
        info.update(grade=round(float(grade), 4), cross_grade=round(float(cross), 4))
    if kind == "hills":
        waves = []
        for _ in range(int(rng.integers(2, 4))):
            lam = rng.uniform(50.0, 160.0)
            amp = rng.uniform(0.3, 1.0) * 0.07 * lam / (2 * np.pi)   # each wave at most 7 % steep
            phi, psi = rng.uniform(0, 2 * np.pi, 2)
            h += amp * np.cos(2 * np.pi * (gx * np.cos(phi) + gy * np.sin(phi)) / lam + psi)
            waves.append([round(float(lam), 1), round(float(amp), 2)])
        info["waves"] = waves
    sv = curve.to_street(np.c_[gx.ravel(), gy.ravel()])[:, 1].reshape(gx.shape)
    on_road = np.abs(sv) < road_half_width
    camber = rng.uniform(0.06, 0.14)
    h += np.where(on_road, camber * (1.0 - (sv / road_half_width) ** 2), 0.0)
    h += np.where(on_road, 0.0, rng.normal(0.0, 0.03, gx.shape))   # lawns and verges are uneven
    info["camber"] = round(float(camber), 3)
    return Terrain(-half, -half, step, h), info

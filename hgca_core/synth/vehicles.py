"""Vehicles for the street scenes: cars of several body shapes, vans, box trucks, buses, bicycles and
motorbikes. Each is centred at the origin, x forward, standing on z = 0; all carry the label CAR.

Materials follow what a LiDAR gets back: tyres and black paint are dark, side windows are glass the
beam mostly passes through (so real scans show a car's lower body and little of its cabin).
"""
from __future__ import annotations

import numpy as np

from hgca_core.synth.assets import CAR, OVERLAP
from hgca_core.synth.materials import DARK, GLASS, PAINT, RETRO
from hgca_core.synth.primitives import _BOX_SIDES, MeshBuilder

SHAPES = ("sedan", "hatchback", "van", "suv", "pickup", "truck", "bus")
SHAPE_P = (0.26, 0.19, 0.14, 0.19, 0.10, 0.07, 0.05)
LENGTH_MAX = {"sedan": 4.9, "hatchback": 4.2, "van": 5.3, "suv": 4.9, "pickup": 5.6, "truck": 7.8, "bus": 12.5}
_TOP = np.array(_BOX_SIDES["+z"])


def pick_shape(rng: np.random.Generator, big: bool = True) -> str:
    """A body shape: mostly cars, sometimes a van, pickup, box truck or bus (`big=False`: cars and vans)."""
    if not big:
        return SHAPES[int(rng.choice(4, p=[0.3, 0.25, 0.2, 0.25]))]
    return SHAPES[int(rng.choice(len(SHAPES), p=SHAPE_P))]


def vehicle(b: MeshBuilder, rng: np.random.Generator, shape: str) -> tuple[float, float]:
    """Any of SHAPES; returns (length, width). One in five is painted black (a dark LiDAR target)."""
    paint = DARK if rng.random() < 0.2 else PAINT
    with b.material(paint):
        if shape == "truck":
            return _box_truck(b, rng)
        if shape == "bus":
            return _bus(b, rng)
        return _car(b, rng, shape, paint)


def _car(b: MeshBuilder, rng: np.random.Generator, shape: str, paint: int) -> tuple[float, float]:
    dims = {"sedan": ((4.4, 4.9), (1.75, 1.85), (1.40, 1.50), 0.31),
            "hatchback": ((3.8, 4.2), (1.70, 1.80), (1.45, 1.55), 0.30),
            "van": ((4.8, 5.3), (1.90, 2.00), (1.95, 2.30), 0.34),
            "suv": ((4.5, 4.9), (1.85, 1.95), (1.65, 1.80), 0.37),
            "pickup": ((5.2, 5.6), (1.90, 2.00), (1.80, 1.90), 0.38)}[shape]
    L, W, H = (rng.uniform(*d) for d in dims[:3])
    r = dims[3] * rng.uniform(0.95, 1.05)
    hx, hy = L / 2, W / 2
    z0 = r * 0.75                                    # sill height: wheels show below
    belt = {"sedan": 0.95, "hatchback": 0.95, "van": 1.0, "suv": 1.05, "pickup": 1.1}[shape] * rng.uniform(0.97, 1.03)
    # cabin footprint: (bottom rear, bottom front, top rear, top front) in x
    cab = {"sedan": (-hx + 0.9, hx - 1.3, -hx + 1.4, hx - 2.0),
           "hatchback": (-hx + 0.15, hx - 1.1, -hx + 0.35, hx - 1.75),
           "van": (-hx + 0.05, hx - 0.8, -hx + 0.1, hx - 1.4),
           "suv": (-hx + 0.25, hx - 1.2, -hx + 0.4, hx - 1.75),
           "pickup": (-0.4, hx - 1.3, -0.3, hx - 1.8)}[shape]
    if shape == "pickup":  # cab + open bed with side walls
        _tapered(b, [-0.4, -hy, z0], [hx, hy, belt], 0.15)
        b.box([-hx, -hy, z0], [-0.4 + OVERLAP, hy, 0.75], CAR, skip=())
        for y0 in (-hy, hy - 0.07):
            b.box([-hx, y0, 0.75 - OVERLAP], [-0.4 + OVERLAP, y0 + 0.07, belt + 0.05], CAR, skip=("-z",))
        b.box([-hx, -hy, 0.75 - OVERLAP], [-hx + 0.07, hy, belt + 0.05], CAR, skip=("-z",))
    else:
        _tapered(b, [-hx, -hy, z0], [hx, hy, belt], 0.12)
    inset = 0.12
    corners = np.array([[cab[0], -hy + 0.05, belt - OVERLAP], [cab[1], -hy + 0.05, belt - OVERLAP],
                        [cab[0], hy - 0.05, belt - OVERLAP], [cab[1], hy - 0.05, belt - OVERLAP],
                        [cab[2], -hy + inset + 0.05, H], [cab[3], -hy + inset + 0.05, H],
                        [cab[2], hy - inset - 0.05, H], [cab[3], hy - inset - 0.05, H]])
    with b.material(GLASS):                          # windows all round, a painted roof
        b.hexahedron(corners, CAR, skip=("-z", "+z"))
    b.add(corners, _TOP, CAR)
    wheel_x = hx - {"van": 0.85, "pickup": 0.95}.get(shape, 0.8) - r * 0.5
    _wheels(b, (-wheel_x, wheel_x), r, hy, 0.24)
    for side in (-1.0, 1.0):  # mirrors, just ahead of the cabin
        y_c = side * (hy + 0.15)
        b.box([cab[1] - 0.25, y_c - 0.1, belt], [cab[1] - 0.05, y_c + 0.1, belt + 0.15], CAR, skip=())
    with b.material(RETRO):                          # number plates
        for x in (-hx - 0.01, hx - 0.01):
            b.box([x, -0.26, z0 + 0.1], [x + 0.02, 0.26, z0 + 0.22], CAR, skip=())
    return L, W


def _wheels(b: MeshBuilder, xs, r: float, hy: float, width: float) -> None:
    with b.material(DARK):
        for x in xs:
            for side in (-1.0, 1.0):
                y_out = side * (hy - 0.02)
                b.cylinder([x, y_out, r], [x, y_out - side * width, r], r, CAR, segments=10)


def _box_truck(b: MeshBuilder, rng: np.random.Generator) -> tuple[float, float]:
    """Box truck: chassis, a cab with a sloped windscreen, a tall cargo box (well above the LiDAR's top beam)."""
    L, W, H = rng.uniform(6.5, 7.8), rng.uniform(2.3, 2.45), rng.uniform(3.0, 3.5)
    r = rng.uniform(0.45, 0.5)
    hx, hy = L / 2, W / 2
    cab = rng.uniform(2.0, 2.4)
    b.box([-hx, -hy + 0.1, r * 0.8], [hx, hy - 0.1, r * 0.8 + 0.35], CAR, skip=())           # chassis
    _tapered(b, [hx - cab, -hy, r * 0.8 + 0.3], [hx, hy, 1.45], 0.05)
    h_cab = rng.uniform(2.5, 2.8)
    corners = np.array([[x, y, z] for z in (1.45 - OVERLAP, h_cab) for y in (-hy + 0.05, hy - 0.05)
                        for x in ((hx - cab, hx - 0.05) if z < 2 else (hx - cab, hx - 0.55))])
    b.hexahedron(corners, CAR, skip=("-z",))
    with b.material(PAINT):                                                                  # white cargo box
        b.box([-hx, -hy, r * 0.8 + 0.3], [hx - cab - 0.1, hy, H], CAR, skip=())
    _wheels(b, (-hx + 1.2, hx - 1.3), r, hy - 0.03, 0.3)
    return L, W


def _bus(b: MeshBuilder, rng: np.random.Generator) -> tuple[float, float]:
    """City bus: low floor, a band of glass along both sides and the front, a roof with equipment boxes."""
    L, W, H = rng.uniform(10.5, 12.5), rng.uniform(2.5, 2.55), rng.uniform(2.95, 3.2)
    r = 0.48
    hx, hy = L / 2, W / 2
    z_win, z_top = rng.uniform(1.0, 1.15), H - rng.uniform(0.35, 0.5)
    b.box([-hx, -hy, 0.3], [hx, hy, z_win + OVERLAP], CAR, skip=())
    with b.material(GLASS):
        b.box([-hx, -hy, z_win], [hx, hy, z_top + OVERLAP], CAR, skip=("-z", "+z"))
    b.box([-hx, -hy, z_top], [hx, hy, H], CAR, skip=("-z",))
    for _ in range(int(rng.integers(1, 3))):
        x0 = rng.uniform(-hx + 1.0, hx - 3.5)
        b.box([x0, -0.7, H - OVERLAP], [x0 + rng.uniform(1.5, 2.5), 0.7, H + 0.3], CAR)
    _wheels(b, (-hx + 2.6, hx - 2.6), r, hy - 0.03, 0.3)
    return L, W


def bicycle(b: MeshBuilder, rng: np.random.Generator) -> None:
    """A bicycle standing upright (1.7 m long, x forward): thin wheels, frame tubes, saddle, handlebar."""
    r = rng.uniform(0.32, 0.36)
    with b.material(DARK):
        for x in (-0.52, 0.52):
            b.cylinder([x, -0.02, r], [x, 0.02, r], r, CAR, segments=12)
    tubes = [([-0.52, 0, r], [0.0, 0, r]), ([0.0, 0, r], [-0.12, 0, r + 0.52]), ([0.0, 0, r], [0.42, 0, r + 0.45]),
             ([-0.12, 0, r + 0.45], [0.42, 0, r + 0.45]), ([0.52, 0, r], [0.42, 0, r + 0.55])]
    for p0, p1 in tubes:
        b.cylinder(p0, p1, 0.02, CAR, segments=6)
    b.box([-0.24, -0.07, r + 0.52], [0.0, 0.07, r + 0.58], CAR, skip=())          # saddle
    b.box([0.39, -0.28, r + 0.55], [0.45, 0.28, r + 0.59], CAR, skip=())          # handlebar


def motorbike(b: MeshBuilder, rng: np.random.Generator) -> None:
    """A parked motorbike (about 2.1 m long): wheels, engine block, tank and seat, handlebar, mirrors."""
    r = rng.uniform(0.29, 0.32)
    with b.material(DARK):
        for x in (-0.72, 0.72):
            b.cylinder([x, -0.06, r], [x, 0.06, r], r, CAR, segments=12)
        b.box([-0.25, -0.17, r - 0.05], [0.35, 0.17, r + 0.35], CAR, skip=())    # engine
    b.box([-0.75, -0.15, r + 0.35], [0.45, 0.15, r + 0.5], CAR, skip=())          # tank and seat
    b.cylinder([0.72, 0, r], [0.6, 0, r + 0.65], 0.03, CAR, segments=6)           # fork
    b.box([0.55, -0.38, r + 0.62], [0.62, 0.38, r + 0.66], CAR, skip=())          # handlebar


def _tapered(b: MeshBuilder, lo, hi, taper: float) -> None:
    """Lower body: a box whose top edges are pulled in at front and back (bonnet and boot slopes)."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    c = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])])
    c[4:, 0] += np.array([taper, -taper, taper, -taper])
    b.hexahedron(c, CAR, skip=())

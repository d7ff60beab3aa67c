"""Procedural street assets built into a `MeshBuilder`, each in its own local frame.

Conventions: z up from the ground the object stands on. Buildings: x along the street (0..width), the
facade at y = 0 facing -y (the street), depth towards +y. Cars: centred, x forward. Parts that touch
overlap by a few centimetres so the shared plane lies strictly inside a solid and the ground truth
drops it (see `Solids.contains`).
"""
from __future__ import annotations

import numpy as np

from hgca_core.synth.primitives import MeshBuilder

ROAD, SIDEWALK, BUILDING, CAR, TREE, POLE, FENCE, SHELTER = range(8)
LABEL_NAMES = ("road", "sidewalk", "building", "car", "tree", "pole", "fence", "shelter")
OVERLAP = 0.05
CAR_SHAPES = ("sedan", "hatchback", "van", "suv", "pickup", "truck")
CAR_SHAPE_P = (0.27, 0.20, 0.13, 0.20, 0.12, 0.08)
CAR_LENGTH_MAX = {"sedan": 4.9, "hatchback": 4.2, "van": 5.3, "suv": 4.9, "pickup": 5.6, "truck": 7.8}


def pick_car_shape(rng: np.random.Generator) -> str:
    """A body shape, mostly cars, sometimes a van, pickup or box truck."""
    return CAR_SHAPES[int(rng.choice(len(CAR_SHAPES), p=CAR_SHAPE_P))]


# ------------------------------------------------------------------------------------------- buildings
def city_building(b: MeshBuilder, rng: np.random.Generator, width: float, depth: float, height: float) -> None:
    """Multi-storey block: optional recessed shop front with pillars and awning, facade segments with
    recesses, bay windows and balconies, cornices, and a flat roof with parapet or a gabled roof."""
    floor_h = rng.uniform(2.9, 3.4)
    shop = rng.random() < 0.6
    ground_h = rng.uniform(3.6, 4.6) if shop else floor_h
    top = height
    gabled = rng.random() < 0.25 and width < 16
    # facade segments along x, each flush or recessed
    n_seg = int(rng.integers(1, 4)) if width > 8 else 1
    cuts = np.sort(rng.uniform(0.25, 0.75, n_seg - 1)) * width if n_seg > 1 else np.zeros(0)
    edges = np.concatenate([[0.0], cuts, [width]])
    recess = np.where(rng.random(n_seg) < 0.3, rng.uniform(0.4, 1.2, n_seg), 0.0)
    if n_seg == 1:
        recess[:] = 0.0
    z_upper = ground_h if shop else 0.0
    windows = rng.random() < 0.85
    win = _window_style(rng)
    for i in range(n_seg):
        xa, xb = edges[i] - (OVERLAP if i > 0 else 0), edges[i + 1] + (OVERLAP if i < n_seg - 1 else 0)
        bottom_open, top_open = shop, not gabled
        if windows:
            facade(b, xa, xb, recess[i], depth, z_upper, top, floor_h, win, bottom_open, top_open)
        else:
            skip = tuple(f for f, hidden in (("-z", not bottom_open), ("+z", not top_open)) if hidden)
            b.box([xa, recess[i], z_upper], [xb, depth, top], BUILDING, skip=skip)
    if shop:
        inset = recess.max() + rng.uniform(0.7, 1.6)
        b.box([OVERLAP, inset, 0.0], [width - OVERLAP, depth - OVERLAP, ground_h + OVERLAP], BUILDING, skip=("-z", "+z"))
        for x0 in (0.0, width - 0.45):  # pillars carrying the overhang
            b.box([x0, 0.0, 0.0], [x0 + 0.45, inset + OVERLAP, ground_h + OVERLAP], BUILDING, skip=("-z", "+z"))
        if width > 10 and rng.random() < 0.6:
            xm = width / 2 - 0.2
            b.box([xm, 0.0, 0.0], [xm + 0.4, inset + OVERLAP, ground_h + OVERLAP], BUILDING, skip=("-z", "+z"))
        if rng.random() < 0.5:  # awning sloping down towards the street
            out, zt = rng.uniform(1.0, 2.0), ground_h - rng.uniform(0.2, 0.5)
            zb = zt - rng.uniform(0.3, 0.6)
            x0, x1 = 0.5, width - 0.5
            # box bit order (x, y, z): y bit 0 is the street edge, lower than the wall edge
            corners = np.array([[x, y, z + dz] for dz in (0.0, 0.08) for y, z in ((-out, zb), (OVERLAP, zt))
                                for x in (x0, x1)])
            b.hexahedron(corners, BUILDING, skip=())
    n_floors = max(1, int((top - ground_h) // floor_h))
    # cornices: a band above the ground floor and one under the roof, on each segment's own facade
    bands = ([ground_h] if shop or rng.random() < 0.4 else []) + ([top - 0.4] if not gabled else [])
    depth_c = rng.uniform(0.12, 0.3)
    for z in bands:
        if z + 0.3 >= top:
            continue
        for i in range(n_seg):
            b.box([edges[i], recess[i] - depth_c, z], [edges[i + 1], recess[i] + OVERLAP, z + 0.3], BUILDING, skip=())
    # per segment: bay windows or balconies on the upper floors
    for i in range(n_seg):
        xa, xb = edges[i] + 0.4, edges[i + 1] - 0.4
        if xb - xa < 1.5 or n_floors < 2:
            continue
        kind = rng.choice(["none", "bay", "balcony", "balcony"])
        y0 = recess[i]
        if kind == "bay" and recess[i] == 0:
            bw = min(xb - xa, rng.uniform(2.0, 4.0))
            bx = rng.uniform(xa, max(xa, xb - bw))
            z0 = ground_h + rng.uniform(0.3, 0.8)
            z1 = min(top - 0.6, z0 + floor_h * int(rng.integers(1, n_floors + 1)))
            b.box([bx, -rng.uniform(0.5, 0.9), z0], [bx + bw, OVERLAP, z1], BUILDING, skip=())
        elif kind == "balcony":
            bw = min(xb - xa, rng.uniform(2.0, 4.5))
            bx = rng.uniform(xa, max(xa, xb - bw))
            bd = rng.uniform(0.9, 1.5)
            for f in range(1, n_floors):
                zf = ground_h + (f - 1) * floor_h if shop else f * floor_h
                if zf + 1.2 > top:
                    break
                b.box([bx, y0 - bd, zf], [bx + bw, y0 + OVERLAP, zf + 0.15], BUILDING, skip=())
                b.box([bx, y0 - bd, zf + 0.15], [bx + bw, y0 - bd + 0.06, zf + 1.05], BUILDING, skip=("-z",))
                for x0 in (bx, bx + bw - 0.06):
                    b.box([x0, y0 - bd + 0.06, zf + 0.15], [x0 + 0.06, y0 + OVERLAP, zf + 1.05], BUILDING, skip=("-z",))
    # roof
    if gabled:
        over = rng.uniform(0.2, 0.5)
        pitch = np.radians(rng.uniform(25, 40))
        span = depth - recess.min() + 2 * over
        b.gable([-over, recess.min() - over, top], [width + over, depth + over], 0.5 * span * np.tan(pitch), BUILDING, 0)
    else:
        t = rng.uniform(0.2, 0.3)
        ph = rng.uniform(0.4, 1.2)
        yf = recess.min()
        for lo, hi in (([0, yf, top - OVERLAP], [width, yf + t, top + ph]),
                       ([0, depth - t, top - OVERLAP], [width, depth, top + ph]),
                       ([0, yf, top - OVERLAP], [t, depth, top + ph]),
                       ([width - t, yf, top - OVERLAP], [width, depth, top + ph])):
            b.box(lo, hi, BUILDING, skip=("-z",))
        for _ in range(int(rng.integers(0, 3))):  # stair houses, machine rooms
            sw, sd = rng.uniform(1.5, min(5.0, width - 1)), rng.uniform(1.5, min(5.0, depth - 1))
            x0, y0 = rng.uniform(0.5, width - sw - 0.5), rng.uniform(yf + 1.0, max(yf + 1.01, depth - sd - 0.5))
            b.box([x0, y0, top - OVERLAP], [x0 + sw, y0 + sd, top + rng.uniform(1.5, 3.0)], BUILDING)


def _window_style(rng: np.random.Generator, small: bool = False) -> dict:
    """One building's window grid: width, pier width, sill height, window height, recess depth."""
    return {"width": rng.uniform(0.9, 1.5) if small else rng.uniform(1.0, 1.9),
            "pier": rng.uniform(1.2, 3.0) if small else rng.uniform(0.5, 1.5),
            "sill": rng.uniform(0.8, 1.0), "height": rng.uniform(1.1, 1.5) if small else rng.uniform(1.3, 1.9),
            "recess": rng.uniform(0.1, 0.15) if small else rng.uniform(0.12, 0.25)}


def facade(b: MeshBuilder, x0: float, x1: float, y0: float, depth: float, z0: float, z1: float, floor_h: float,
           win: dict, bottom_open: bool, top_open: bool) -> None:
    """A block [x0, x1] x [y0, depth] x [z0, z1] whose front (y = y0) has a grid of recessed windows.

    The body starts `recess` behind the front; piers (between window columns) and spandrels (between
    window rows) fill the front layer, so each window is a pocket whose back is the body's face.
    `bottom_open` / `top_open`: whether the block's underside / top is exposed (overhang, flat roof).
    """
    w, pier, r = win["width"], win["pier"], win["recess"]
    n_col = int((x1 - x0 - pier) // (w + pier))
    sill = win["sill"]
    wh = min(win["height"], floor_h - sill - 0.3)
    rows = []
    zf = z0
    while wh > 0.5 and zf + sill + wh < z1 - 0.3:
        rows.append((zf + sill, zf + sill + wh))
        zf += floor_h
    skip_b = () if bottom_open else ("-z",)
    skip_t = () if top_open else ("+z",)
    if n_col < 1 or not rows:
        b.box([x0, y0, z0], [x1, depth, z1], BUILDING, skip=skip_b + skip_t)
        return
    b.box([x0, y0 + r, z0], [x1, depth, z1], BUILDING, skip=skip_b + skip_t)
    edge = (x1 - x0 - n_col * w - (n_col - 1) * pier) / 2
    xs = x0 + edge + np.arange(n_col) * (w + pier)                   # left edges of the window columns
    pier_spans = [(x0, xs[0])] + [(a + w, a + w + pier) for a in xs[:-1]] + [(xs[-1] + w, x1)]
    front = [y0, y0 + r + OVERLAP]
    for a, z in pier_spans:
        b.box([a, front[0], z0], [z, front[1], z1], BUILDING, skip=skip_b + skip_t)
    bands = [(z0, rows[0][0])] + [(rows[k][1], rows[k + 1][0]) for k in range(len(rows) - 1)] + [(rows[-1][1], z1)]
    for k, (za, zb) in enumerate(bands):
        sk = (skip_b if k == 0 else ()) + (skip_t if k == len(bands) - 1 else ())
        b.box([x0, front[0], za], [x1, front[1], zb], BUILDING, skip=sk)


def house(b: MeshBuilder, rng: np.random.Generator, width: float, depth: float) -> None:
    """Suburban house: one or two storeys, gabled roof with eaves, porch, optional garage and chimney."""
    storeys = 1 if rng.random() < 0.4 else 2
    wall_h = storeys * rng.uniform(2.7, 3.1) + rng.uniform(0.2, 0.6)
    win = _window_style(rng, small=True)
    facade(b, 0.0, width, 0.0, depth, 0.0, wall_h, (wall_h - 0.3) / storeys, win, False, False)
    over = rng.uniform(0.3, 0.6)
    pitch = np.radians(rng.uniform(25, 45))
    ridge_x = rng.random() < 0.7
    span = (depth if ridge_x else width) + 2 * over
    rise = 0.5 * span * np.tan(pitch)
    b.gable([-over, -over, wall_h], [width + over, depth + over], rise, BUILDING, 0 if ridge_x else 1)
    if rng.random() < 0.5:
        cx, cy = rng.uniform(0.8, width - 1.6), rng.uniform(depth * 0.3, depth * 0.7)
        b.box([cx, cy, wall_h], [cx + 0.7, cy + 0.7, wall_h + rise + rng.uniform(0.5, 1.2)], BUILDING, skip=("-z",))
    if rng.random() < 0.6:  # porch roof on posts
        pw = rng.uniform(2.0, min(4.0, width - 1.0))
        px = rng.uniform(0.5, width - pw - 0.5)
        pd = rng.uniform(1.2, 2.2)
        ph = rng.uniform(2.4, 2.8)
        b.box([px, -pd, ph], [px + pw, OVERLAP, ph + 0.15], BUILDING, skip=())
        for x0 in (px, px + pw - 0.15):
            b.box([x0, -pd, 0.0], [x0 + 0.15, -pd + 0.15, ph + OVERLAP], BUILDING, skip=("-z", "+z"))
        b.box([px - 0.3, -pd, 0.0], [px + pw + 0.3, OVERLAP, 0.35], BUILDING, skip=("-z",))  # deck
    if rng.random() < 0.3:  # bay window
        bw = rng.uniform(1.5, 2.5)
        bx = rng.uniform(0.5, width - bw - 0.5)
        b.box([bx, -0.6, 0.5], [bx + bw, OVERLAP, 2.4], BUILDING, skip=())


def garage(b: MeshBuilder, rng: np.random.Generator, width: float, depth: float) -> None:
    """Garage: low box with a flat or gabled roof and a recessed door."""
    h = rng.uniform(2.6, 3.2)
    b.box([0, 0.25, 0], [width, depth, h], BUILDING, skip=("-z",))
    b.box([0, 0, 0], [0.3, 0.25 + OVERLAP, h], BUILDING, skip=("-z",))
    b.box([width - 0.3, 0, 0], [width, 0.25 + OVERLAP, h], BUILDING, skip=("-z",))
    b.box([0, 0, h - 0.5], [width, 0.25 + OVERLAP, h], BUILDING, skip=())
    if rng.random() < 0.5:
        b.gable([-0.2, -0.2, h], [width + 0.2, depth + 0.2], rng.uniform(0.8, 1.6), BUILDING, 1)


def simple_block(b: MeshBuilder, rng: np.random.Generator, width: float, depth: float, height: float) -> None:
    """Plain building for rows far from the street (few faces: seen only by wide regions)."""
    b.box([0, 0, 0], [width, depth, height], BUILDING)
    if rng.random() < 0.5:
        b.box([0, 0, height - OVERLAP], [width, 0.3, height + 1.0], BUILDING)


# ------------------------------------------------------------------------------------------------- cars
def car(b: MeshBuilder, rng: np.random.Generator, shape: str) -> tuple[float, float]:
    """A parked car centred at the origin, x forward; returns (length, width)."""
    if shape == "truck":
        return _box_truck(b, rng)
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
        _tapered(b, [-0.4, -hy, z0], [hx, hy, belt], 0.15, CAR)
        b.box([-hx, -hy, z0], [-0.4 + OVERLAP, hy, 0.75], CAR, skip=())
        for y0 in (-hy, hy - 0.07):
            b.box([-hx, y0, 0.75 - OVERLAP], [-0.4 + OVERLAP, y0 + 0.07, belt + 0.05], CAR, skip=("-z",))
        b.box([-hx, -hy, 0.75 - OVERLAP], [-hx + 0.07, hy, belt + 0.05], CAR, skip=("-z",))
    else:
        _tapered(b, [-hx, -hy, z0], [hx, hy, belt], 0.12, CAR)
    inset = 0.12
    corners = np.array([[cab[0], -hy + 0.05, belt - OVERLAP], [cab[1], -hy + 0.05, belt - OVERLAP],
                        [cab[0], hy - 0.05, belt - OVERLAP], [cab[1], hy - 0.05, belt - OVERLAP],
                        [cab[2], -hy + inset + 0.05, H], [cab[3], -hy + inset + 0.05, H],
                        [cab[2], hy - inset - 0.05, H], [cab[3], hy - inset - 0.05, H]])
    b.hexahedron(corners, CAR, skip=("-z",))
    wheel_x = hx - {"van": 0.85, "pickup": 0.95}.get(shape, 0.8) - r * 0.5
    for x in (-wheel_x, wheel_x):
        for side in (-1.0, 1.0):
            y_out = side * (hy - 0.02)
            b.cylinder([x, y_out, r], [x, y_out - side * 0.24, r], r, CAR, segments=10)
    for side in (-1.0, 1.0):  # mirrors, just ahead of the cabin
        y_c = side * (hy + 0.15)
        b.box([cab[1] - 0.25, y_c - 0.1, belt], [cab[1] - 0.05, y_c + 0.1, belt + 0.15], CAR, skip=())
    return L, W


def _box_truck(b: MeshBuilder, rng: np.random.Generator) -> tuple[float, float]:
    """Box truck: chassis, a cab with a sloped windscreen, a tall cargo box (well above the LiDAR's top beam)."""
    L, W, H = rng.uniform(6.5, 7.8), rng.uniform(2.3, 2.45), rng.uniform(3.0, 3.5)
    r = rng.uniform(0.45, 0.5)
    hx, hy = L / 2, W / 2
    cab = rng.uniform(2.0, 2.4)
    b.box([-hx, -hy + 0.1, r * 0.8], [hx, hy - 0.1, r * 0.8 + 0.35], CAR, skip=())           # chassis
    _tapered(b, [hx - cab, -hy, r * 0.8 + 0.3], [hx, hy, 1.45], 0.05, CAR)
    h_cab = rng.uniform(2.5, 2.8)
    corners = np.array([[x, y, z] for z in (1.45 - OVERLAP, h_cab) for y in (-hy + 0.05, hy - 0.05)
                        for x in ((hx - cab, hx - 0.05) if z < 2 else (hx - cab, hx - 0.55))])
    b.hexahedron(corners, CAR, skip=("-z",))
    b.box([-hx, -hy, r * 0.8 + 0.3], [hx - cab - 0.1, hy, H], CAR, skip=())                  # cargo box
    for x in (-hx + 1.2, hx - 1.3):
        for side in (-1.0, 1.0):
            y_out = side * (hy - 0.05)
            b.cylinder([x, y_out, r], [x, y_out - side * 0.3, r], r, CAR, segments=10)
    return L, W


def _tapered(b: MeshBuilder, lo, hi, taper: float, label: int) -> None:
    """Lower body: a box whose top edges are pulled in at front and back (bonnet and boot slopes)."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    c = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])])
    c[4:, 0] += np.array([taper, -taper, taper, -taper])
    b.hexahedron(c, label, skip=())


# ------------------------------------------------------------------------------------ vegetation, furniture
def tree(b: MeshBuilder, rng: np.random.Generator, scale: float = 1.0, conifer: bool = False) -> float:
    """Trunk plus a canopy of clustered blobs (or stacked cones for a conifer); returns the canopy radius."""
    trunk_h = rng.uniform(1.8, 3.2) * scale
    r_trunk = rng.uniform(0.12, 0.25) * scale
    if conifer:
        h = rng.uniform(5.0, 10.0) * scale
        base = rng.uniform(1.5, 2.5) * scale
        b.cylinder([0, 0, 0], [0, 0, trunk_h * 0.5 + OVERLAP], r_trunk, TREE, segments=8)
        n = int(rng.integers(2, 4))
        z = trunk_h * 0.5
        for i in range(n):
            seg = (h - z) / (n - i) * 1.4
            rad = base * (1.0 - i / (n + 0.5))
            b.cylinder([0, 0, z], [0, 0, z + seg], rad, TREE, segments=10, radius_top=0.05)
            z += seg * 0.55
        return base
    rc = rng.uniform(1.5, 3.0) * scale
    zc = trunk_h + rc * 0.7
    b.cylinder([0, 0, 0], [0, 0, zc], r_trunk, TREE, segments=8)
    n = int(rng.integers(3, 7))
    b.ellipsoid([0, 0, zc], rc * 0.8, rc * 0.7, TREE)
    for _ in range(n):
        ang = rng.uniform(0, 2 * np.pi)
        d = rng.uniform(0.3, 0.65) * rc
        rad = rng.uniform(0.45, 0.75) * rc
        b.ellipsoid([d * np.cos(ang), d * np.sin(ang), zc + rng.uniform(-0.3, 0.5) * rc], rad, rad * rng.uniform(0.7, 1.0), TREE)
    return rc


def bush(b: MeshBuilder, rng: np.random.Generator) -> None:
    r = rng.uniform(0.5, 1.1)
    b.ellipsoid([0, 0, r * 0.7], r, r * 0.7, TREE)


def street_lamp(b: MeshBuilder, rng: np.random.Generator) -> None:
    """Pole with an arm reaching over the road (-y) and a lamp head."""
    h = rng.uniform(6.0, 9.0)
    arm = rng.uniform(1.2, 2.5)
    b.cylinder([0, 0, 0], [0, 0, h], rng.uniform(0.07, 0.12), POLE, segments=8)
    b.box([-0.05, -arm, h - 0.3], [0.05, 0.05, h - 0.2], POLE, skip=())
    b.box([-0.2, -arm - 0.3, h - 0.45], [0.2, -arm + 0.3, h - 0.25], POLE, skip=())
    b.box([-0.18, -0.18, 0.0], [0.18, 0.18, 0.6], POLE)  # base


def sign_pole(b: MeshBuilder, rng: np.random.Generator) -> None:
    h = rng.uniform(2.3, 3.2)
    b.cylinder([0, 0, 0], [0, 0, h], 0.04, POLE, segments=6)
    s = rng.uniform(0.5, 0.8)
    b.box([-s / 2, -0.08, h - s], [s / 2, -0.04, h], POLE, skip=())


def traffic_light(b: MeshBuilder, rng: np.random.Generator) -> None:
    h = rng.uniform(3.5, 5.5)
    b.cylinder([0, 0, 0], [0, 0, h], 0.1, POLE, segments=8)
    arm = rng.uniform(2.0, 4.0)
    b.box([-0.06, -arm, h - 0.15], [0.06, 0.05, h], POLE, skip=())
    b.box([-0.18, -arm, h - 1.1], [0.18, -arm + 0.3, h - 0.1], POLE, skip=())
    b.box([-0.18, 0.1, 2.0], [0.18, 0.4, 2.9], POLE, skip=())


def bollard(b: MeshBuilder, rng: np.random.Generator) -> None:
    b.cylinder([0, 0, 0], [0, 0, rng.uniform(0.7, 1.0)], 0.1, POLE, segments=8)


def bench(b: MeshBuilder, rng: np.random.Generator) -> None:
    L = rng.uniform(1.5, 2.2)
    b.box([-L / 2, 0, 0.42], [L / 2, 0.45, 0.48], POLE, skip=())
    b.box([-L / 2, 0.4, 0.48], [L / 2, 0.45, 0.9], POLE, skip=())
    for x in (-L / 2 + 0.1, L / 2 - 0.15):
        b.box([x, 0.05, 0], [x + 0.05, 0.4, 0.42 + OVERLAP], POLE, skip=("-z", "+z"))


def trash_bin(b: MeshBuilder, rng: np.random.Generator) -> None:
    b.cylinder([0, 0, 0], [0, 0, rng.uniform(0.8, 1.1)], rng.uniform(0.25, 0.35), POLE, segments=10)


def bus_shelter(b: MeshBuilder, rng: np.random.Generator) -> float:
    """Shelter along x (0..length), open towards -y (the road), back wall at +y; returns its length."""
    L = rng.uniform(3.0, 5.0)
    D = rng.uniform(1.3, 1.8)
    h = rng.uniform(2.3, 2.6)
    b.box([-0.1, -0.3, h], [L + 0.1, D + 0.1, h + 0.15], SHELTER, skip=())
    b.box([0.05, D - 0.06, 0.1], [L - 0.05, D, h + OVERLAP], SHELTER, skip=())
    for x0 in (0.0, L - 0.05):
        b.box([x0, D * 0.35, 0.1], [x0 + 0.05, D - 0.06 + OVERLAP, h + OVERLAP], SHELTER, skip=())
        b.box([x0, D - 0.06, 0.0], [x0 + 0.08, D, h + OVERLAP], SHELTER, skip=("-z", "+z"))
    b.box([0.5, D - 0.5, 0.42], [L - 0.5, D - 0.06 + OVERLAP, 0.48], SHELTER, skip=())
    return L


def fence(b: MeshBuilder, rng: np.random.Generator, length: float, kind: str) -> None:
    """Fence along x from 0 to length: 'picket' (posts and rails), 'panel', 'wall' or 'hedge'."""
    if kind == "hedge":
        t, h = rng.uniform(0.6, 1.0), rng.uniform(1.0, 1.8)
        b.box([0, 0, 0], [length, t, h], FENCE)
    elif kind == "wall":
        t, h = rng.uniform(0.2, 0.35), rng.uniform(1.2, 2.5)
        b.box([0, 0, 0], [length, t, h], FENCE)
        b.box([-0.03, -0.03, h - OVERLAP], [length + 0.03, t + 0.03, h + 0.08], FENCE)
    elif kind == "panel":
        h = rng.uniform(1.5, 2.0)
        b.box([0, 0, 0.05], [length, 0.04, h], FENCE, skip=())
        for x in np.arange(0.0, length - 0.05, 2.4):
            b.box([x, -0.04, 0], [x + 0.1, 0.08, h + 0.1], FENCE)
    else:  # picket: posts, two rails
        h = rng.uniform(0.9, 1.3)
        step = rng.uniform(1.8, 2.6)
        for x in np.append(np.arange(0.0, length - 0.1, step), length - 0.1):
            b.box([x, 0, 0], [x + 0.1, 0.1, h], FENCE)
        for z in (0.3, h - 0.25):
            b.box([0, 0.1 - OVERLAP, z], [length, 0.14, z + 0.1], FENCE, skip=())
        # boards: thin slats every 15 cm make a see-through fence; model them as a low-res slatted panel
        n = int(length / 0.3)
        if n > 0:
            xs = np.linspace(0.1, length - 0.2, n)
            for x in xs:
                b.box([x, 0.14 - OVERLAP, 0.05], [x + 0.12, 0.16, h - 0.05], FENCE, skip=())

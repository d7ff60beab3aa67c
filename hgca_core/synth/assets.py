"""Procedural street assets built into a `MeshBuilder`, each in its own local frame.

Conventions: z up from the ground the object stands on. Buildings: x along the street (0..width), the
facade at y = 0 facing -y (the street), depth towards +y. Cars: centred, x forward. Parts that touch
overlap by a few centimetres so the shared plane lies strictly inside a solid and the ground truth
drops it (see `Solids.contains`).
"""
from __future__ import annotations

import numpy as np

from hgca_core.synth.materials import DARK, WINDOW
from hgca_core.synth.primitives import DEFAULT_MATERIAL, MeshBuilder

ROAD, SIDEWALK, BUILDING, CAR, TREE, POLE, FENCE, SHELTER, PERSON = range(9)
LABEL_NAMES = ("road", "sidewalk", "building", "car", "tree", "pole", "fence", "shelter", "person")
OVERLAP = 0.05


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
        if rng.random() < 0.8:  # shop windows across the front, a door gap
            door = rng.uniform(0.6, width - 2.0)
            yg = inset - 0.04
            with b.material(WINDOW):
                for xa, xb in ((0.45, door), (door + 1.1, width - 0.45)):
                    if xb - xa > 0.5:
                        b.quad([[xa, yg, 0.4], [xb, yg, 0.4], [xb, yg, ground_h - 0.4], [xa, yg, ground_h - 0.4]], BUILDING)
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
            "recess": rng.uniform(0.1, 0.15) if small else rng.uniform(0.12, 0.25),
            "glass": rng.random() < 0.85}


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
    if win.get("glass", False):  # panes a few centimetres in front of the pocket's back
        yg = y0 + r - 0.03
        with b.material(WINDOW):
            for a in xs:
                for za, zb in rows:
                    b.quad([[a, yg, za], [a + w, yg, za], [a + w, yg, zb], [a, yg, zb]], BUILDING)


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


def low_shop(b: MeshBuilder, rng: np.random.Generator, width: float, depth: float) -> float:
    """Single-storey shop, 3.2-5 m: a flat roof behind a parapet, a glass front with a door, often a sign
    board or an awning. Returns its height (walls that end low are what real streets mostly hold)."""
    h = rng.uniform(3.2, 5.0)
    b.box([0, 0, 0], [width, depth, h], BUILDING, skip=("-z",))
    parapet = rng.uniform(0.2, 0.9)
    if rng.random() < 0.7:  # parapet around the roof's front and sides
        for lo, hi in (([0, 0], [width, 0.25]), ([0, 0], [0.25, depth]), ([width - 0.25, 0], [width, depth])):
            b.box([lo[0], lo[1], h - OVERLAP], [hi[0], hi[1], h + parapet], BUILDING, skip=())
    if rng.random() < 0.8:  # shop windows, a door gap
        door = rng.uniform(0.5, max(0.6, width - 1.8))
        with b.material(WINDOW):
            for xa, xb in ((0.3, door), (door + 1.1, width - 0.3)):
                if xb - xa > 0.5:
                    b.quad([[xa, -0.02, 0.4], [xb, -0.02, 0.4], [xb, -0.02, h - 0.9], [xa, -0.02, h - 0.9]], BUILDING)
    if rng.random() < 0.5:  # sign board over the front
        b.box([0.4, -0.2, h - 0.8], [width - 0.4, OVERLAP, h - 0.15], BUILDING, skip=())
    elif rng.random() < 0.6:  # awning sloping down towards the street
        out, zt = rng.uniform(1.0, 2.0), h - rng.uniform(0.6, 1.0)
        zb = zt - rng.uniform(0.3, 0.6)
        corners = np.array([[x, y, z + dz] for dz in (0.0, 0.08) for y, z in ((-out, zb), (OVERLAP, zt))
                            for x in (0.3, width - 0.3)])
        b.hexahedron(corners, BUILDING, skip=())
    return h


def simple_block(b: MeshBuilder, rng: np.random.Generator, width: float, depth: float, height: float) -> None:
    """Plain building for rows far from the street (few faces: seen only by wide regions)."""
    b.box([0, 0, 0], [width, depth, height], BUILDING)
    if rng.random() < 0.5:
        b.box([0, 0, height - OVERLAP], [width, 0.3, height + 1.0], BUILDING)




def row_house(b: MeshBuilder, rng: np.random.Generator, width: float, depth: float, storeys: int) -> None:
    """Terraced house: a narrow facade of 2-3 storeys, the roof ridge along the street, maybe a dormer."""
    floor_h = rng.uniform(2.7, 3.1)
    wall_h = storeys * floor_h + rng.uniform(0.2, 0.5)
    facade(b, 0.0, width, 0.0, depth, 0.0, wall_h, floor_h, _window_style(rng, small=True), False, False)
    over = rng.uniform(0.2, 0.4)
    rise = 0.5 * (depth + 2 * over) * np.tan(np.radians(rng.uniform(30, 45)))
    b.gable([-OVERLAP, -over, wall_h], [width + OVERLAP, depth + over], rise, BUILDING, 0)
    if rng.random() < 0.4 and width > 4.0:
        dw = rng.uniform(1.5, min(3.0, width - 1.5))
        dx = rng.uniform(0.5, width - dw - 0.5)
        b.box([dx, depth * 0.22, wall_h + 0.2], [dx + dw, depth * 0.45, wall_h + rise * 0.55], BUILDING, skip=("-z",))
    if rng.random() < 0.5:  # front steps
        b.box([width * 0.3, -0.9, 0.0], [width * 0.3 + 1.2, OVERLAP, 0.45], BUILDING)


def warehouse(b: MeshBuilder, rng: np.random.Generator, width: float, depth: float,
              heights: tuple[float, float] = (6.0, 9.5)) -> None:
    """Long low hall: a plain (often dark) cladding wall with recessed roller doors and a strip of windows."""
    h = rng.uniform(*heights)
    doors = []
    x = rng.uniform(1.5, 4.0)
    while x + 4.5 < width - 1.0:
        if rng.random() < 0.6:
            doors.append(x)
        x += rng.uniform(5.0, 9.0)
    with b.material(DARK if rng.random() < 0.35 else DEFAULT_MATERIAL):
        b.box([0, 0.3, 0], [width, depth, h], BUILDING)
        cuts = [0.0] + [v for d in doors for v in (d, d + 4.0)] + [width]
        for xa, xb in zip(cuts[::2], cuts[1::2]):                    # wall between the door pockets
            if xb - xa > 0.05:
                b.box([xa, 0.0, 0.0], [xb, 0.3 + OVERLAP, h], BUILDING)
        for d in doors:
            b.box([d - OVERLAP, 0.0, 4.2], [d + 4.0 + OVERLAP, 0.3 + OVERLAP, h], BUILDING)
    if rng.random() < 0.6:
        with b.material(WINDOW):
            zw = h - rng.uniform(1.2, 1.8)
            b.quad([[0.5, -0.01, zw], [width - 0.5, -0.01, zw], [width - 0.5, -0.01, zw + 0.8], [0.5, -0.01, zw + 0.8]],
                   BUILDING)

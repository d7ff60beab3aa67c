"""Street scene layout: a main street along x through a 120 x 120 m block, seeded.

World frame = scene frame: z up, the road surface at z = 0, the main street centred on y = 0. Styles:
"city" (dense rows of 6-25 m blocks, shops, narrow gaps, street furniture) and "suburb" (gabled houses
set back behind yards, fences and hedges, garages and driveways, many trees).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from hgca_core.synth import assets as A
from hgca_core.synth.primitives import MeshBuilder, Solids

STYLES = ("city", "suburb")
EXTENT = 60.0       # half size of the scene square (metres)
DRIVE_STEP = 0.5    # spacing of drive samples (metres)
BLOCK = 40.0        # street stretch over which parked cars are counted (metres)


@dataclass
class StreetScene:
    """A generated scene. `drive` is the ego sensor path (M, 3), about 2 m above the road along the main
    street; `street_box` the main street corridor (road + sidewalks) as xmin, ymin, xmax, ymax (world);
    `solids` the volumes whose interior holds no visible surface (used to clean the ground truth)."""

    mesh: trimesh.Trimesh
    face_labels: np.ndarray
    drive: np.ndarray
    street_box: np.ndarray
    style: str
    seed: int
    solids: Solids
    layout: dict = field(default_factory=dict)


def make_scene(seed: int, style: str | None = None) -> StreetScene:
    """The scene named by `seed` (and `style`; by default the seed picks it)."""
    rng = np.random.default_rng([int(seed), 7919])
    picked = STYLES[int(rng.integers(0, 2))]
    style = picked if style is None else style
    if style not in STYLES:
        raise ValueError(f"unknown style {style!r}; use one of {', '.join(STYLES)}")
    city = style == "city"
    L = _Layout(
        hw=rng.uniform(5.5, 8.0) if city else rng.uniform(4.5, 6.0),
        sw=rng.uniform(2.5, 5.0) if city else rng.uniform(1.8, 3.0),
        hs=rng.uniform(0.11, 0.14),
        cross=rng.random() < (0.5 if city else 0.35),
        xc=rng.uniform(-25.0, 25.0),
        hw2=rng.uniform(4.0, 6.5) if city else rng.uniform(3.5, 5.0),
    )
    b = MeshBuilder()
    b.ground_tiles(-EXTENT, -EXTENT, EXTENT, EXTENT, 0.0, 8.0, A.ROAD)
    _sidewalks(b, L)
    furniture_blocked = _street_furniture(b, rng, L, city)
    parked = _parked_cars(b, rng, L, furniture_blocked, city)
    driveway = 0 if city else _suburb_rows(b, rng, L)
    if city:
        _city_rows(b, rng, L)
    mesh, labels, solids = b.build()
    drive, direction = _drive(rng, L)
    y_out = L.hw + L.sw
    layout = {"road_half_width": L.hw, "sidewalk_width": L.sw, "sidewalk_height": L.hs,
              "crossroad_x": L.xc if L.cross else None, "crossroad_half_width": L.hw2 if L.cross else None,
              "parked_cars": parked, "driveway_cars": driveway, "drive_direction": direction, "faces": int(len(mesh.faces))}
    return StreetScene(mesh, labels, drive, np.array([-EXTENT, -y_out, EXTENT, y_out]), style, int(seed),
                       solids, layout)


@dataclass
class _Layout:
    hw: float      # road half width (curb to centre line)
    sw: float      # sidewalk width
    hs: float      # sidewalk (curb) height
    cross: bool    # has a crossroad
    xc: float      # crossroad centre x
    hw2: float     # crossroad half width

    def x_free(self, x: float, margin: float) -> bool:
        """Whether x is clear of the cross street (road and sidewalks) by `margin`."""
        return not self.cross or abs(x - self.xc) > self.hw2 + self.sw + margin


def _sidewalks(b: MeshBuilder, L: _Layout) -> None:
    """Raised sidewalks with curbs along the main street (and the cross street)."""
    spans = [(-EXTENT, L.xc - L.hw2), (L.xc + L.hw2, EXTENT)] if L.cross else [(-EXTENT, EXTENT)]
    for x0, x1 in spans:
        for s in (1, -1):
            y0, y1 = sorted((s * L.hw, s * (L.hw + L.sw)))
            b.box([x0, y0, 0.0], [x1, y1, L.hs], A.SIDEWALK)
    if L.cross:
        for x0, x1 in ((L.xc - L.hw2 - L.sw, L.xc - L.hw2), (L.xc + L.hw2, L.xc + L.hw2 + L.sw)):
            for y0, y1 in ((L.hw + L.sw - A.OVERLAP, EXTENT), (-EXTENT, -L.hw - L.sw + A.OVERLAP)):
                b.box([x0, y0, 0.0], [x1, y1, L.hs], A.SIDEWALK)


def _side_frame(s: int, x: float, y: float, z: float = 0.0) -> tuple[float, list[float]]:
    """(yaw, offset) placing an object whose local -y faces the main street, on side s (+1 north, -1 south)."""
    return (0.0, [x, y, z]) if s > 0 else (np.pi, [x, -y, z])


def _street_furniture(b: MeshBuilder, rng: np.random.Generator, L: _Layout, city: bool) -> list[tuple[int, float, float]]:
    """Lamps, street trees, signs, a bus shelter, benches, bins, traffic lights. Returns (side, x0, x1) spans
    at the curb that parked cars must leave free (bus stops)."""
    blocked: list[tuple[int, float, float]] = []
    z = L.hs
    if rng.random() < (0.6 if city else 0.3):  # bus shelter, against the back of the sidewalk
        s = int(rng.choice([-1, 1]))
        for _ in range(10):
            x = rng.uniform(-45, 40)
            if L.x_free(x, 2.0) and L.x_free(x + 5, 2.0):
                break
        with b.placed(*_side_frame(s, x, L.hw + max(0.6, L.sw - 1.9), z)):
            length = A.bus_shelter(b, rng)
        blocked.append((s, (x if s > 0 else x - length) - 6.0, (x + length if s > 0 else x) + 6.0))
    for s in (1, -1):
        occupied: list[float] = []
        if rng.random() < 0.85:  # street lamps near the curb
            step = rng.uniform(18.0, 30.0)
            for x in np.arange(-EXTENT + rng.uniform(2, step), EXTENT - 2, step):
                if L.x_free(x, 0.5):
                    with b.placed(*_side_frame(s, x, L.hw + 0.45, z)):
                        A.street_lamp(b, rng)
                    occupied.append(x)
        if rng.random() < (0.55 if city else 0.7):  # a row of street trees
            step = rng.uniform(7.0, 13.0)
            scale = rng.uniform(0.8, 1.2)
            for x in np.arange(-EXTENT + rng.uniform(2, step), EXTENT - 2, step):
                if L.x_free(x, 1.5) and all(abs(x - o) > 2.0 for o in occupied) and rng.random() < 0.9:
                    with b.placed(*_side_frame(s, x, L.hw + min(1.2, L.sw / 2), z)):
                        A.tree(b, rng, scale)
                    occupied.append(x)
        for _ in range(int(rng.integers(1, 4))):  # sign poles
            x = rng.uniform(-EXTENT + 2, EXTENT - 2)
            if L.x_free(x, 0.5) and all(abs(x - o) > 1.5 for o in occupied):
                with b.placed(*_side_frame(s, x, L.hw + 0.35, z)):
                    A.sign_pole(b, rng)
                occupied.append(x)
        if city:
            for _ in range(int(rng.integers(0, 4))):
                x = rng.uniform(-EXTENT + 2, EXTENT - 2)
                if not L.x_free(x, 0.5) or any(abs(x - o) < 2.5 for o in occupied):
                    continue
                kind = rng.integers(0, 3)
                with b.placed(*_side_frame(s, x, L.hw + (0.5 if kind == 2 else L.sw * 0.6), z)):
                    (A.bench, A.trash_bin, A.bollard)[kind](b, rng)
                occupied.append(x)
    if L.cross and city and rng.random() < 0.7:  # traffic lights on the corners, arms over the main road
        for sx in (-1, 1):
            for s in (-1, 1):
                if rng.random() < 0.75:
                    with b.placed(*_side_frame(s, L.xc + sx * (L.hw2 + 0.5), L.hw + 0.5, z)):
                        A.traffic_light(b, rng)
    return blocked


def _free_position(rng: np.random.Generator, lo: float, hi: float, length: float, taken: list[tuple[float, float]],
                   gap: float) -> float | None:
    """A uniform centre for an interval of `length` in [lo, hi]; if it collides, moved to the nearest free
    spot (the paper moves colliding cars). None when nothing is free."""
    half = length / 2 + gap
    x = rng.uniform(lo + half, hi - half)
    bad = sorted((a - half, z + half) for a, z in taken)
    free, cur = [], lo + half
    for a, z in bad:
        if a > cur:
            free.append((cur, min(a, hi - half)))
        cur = max(cur, z)
    if cur < hi - half:
        free.append((cur, hi - half))
    free = [(a, z) for a, z in free if z >= a]
    if not free:
        return None
    return float(min((np.clip(x, a, z) for a, z in free), key=lambda c: abs(c - x)))


def _parked_cars(b: MeshBuilder, rng: np.random.Generator, L: _Layout, blocked: list[tuple[int, float, float]],
                 city: bool) -> list[dict]:
    """Cars parked at both curbs of the main street, never overlapping. As in Karton City, the count per
    side of a street stretch is Poisson(2), at most 7; our stretch is one 40 m block (a region's length),
    so a sample sees about as many cars as a Karton City one."""
    out = []
    for s in (1, -1):
        taken: list[tuple[float, float]] = [(x0, x1) for side, x0, x1 in blocked if side == s]
        if L.cross:
            taken.append((L.xc - L.hw2 - 5.0, L.xc + L.hw2 + 5.0))
        for x_lo in np.arange(-EXTENT, EXTENT - 1.0, BLOCK):
            for _ in range(min(int(rng.poisson(2.0)), 7)):
                shape = A.pick_car_shape(rng)
                length = A.CAR_LENGTH_MAX[shape]
                x = _free_position(rng, max(x_lo, -EXTENT + 1), min(x_lo + BLOCK, EXTENT - 1), length, taken, 0.6)
                if x is None:
                    continue
                taken.append((x - length / 2, x + length / 2))
                y = s * (L.hw - 1.0 - rng.uniform(0.15, 0.4))
                yaw = (0.0 if rng.random() < 0.5 else np.pi) + np.radians(rng.normal(0.0, 1.5))
                with b.placed(yaw, [x, y, 0.0]):
                    A.car(b, rng, shape)
                out.append({"shape": shape, "x": round(float(x), 2), "y": round(float(y), 2),
                            "yaw_deg": round(float(np.degrees(yaw)), 1)})
    if L.cross and city:  # a few on the cross street too
        for sx in (-1, 1):
            for _ in range(min(int(rng.poisson(1.0)), 3)):
                y = rng.uniform(L.hw + L.sw + 4, EXTENT - 4) * rng.choice([-1, 1])
                shape = A.pick_car_shape(rng)
                with b.placed(np.pi / 2 + (0.0 if rng.random() < 0.5 else np.pi), [L.xc + sx * (L.hw2 - 1.2), y, 0.0]):
                    A.car(b, rng, shape)
    return out


def _lots(rng: np.random.Generator, L: _Layout, wmin: float, wmax: float, gap_p: float, gap_range: tuple[float, float],
          margin: float = 0.0) -> list[tuple[float, float]]:
    """Lots (x0, x1) along a building row, skipping the cross street; gaps with probability gap_p."""
    lots, x = [], -EXTENT
    while x < EXTENT - wmin * 0.6:
        w = min(rng.uniform(wmin, wmax), EXTENT - x)
        if L.cross and x + w > L.xc - L.hw2 - L.sw - margin and x < L.xc + L.hw2 + L.sw + margin:
            x = L.xc + L.hw2 + L.sw + margin + rng.uniform(0.0, 1.0)
            continue
        lots.append((x, x + w))
        # attached neighbours overlap a little, so the party wall lies inside a solid and leaves the truth
        x += w + (rng.uniform(*gap_range) if rng.random() < gap_p else -A.OVERLAP)
    return lots


def _city_rows(b: MeshBuilder, rng: np.random.Generator, L: _Layout) -> None:
    """Rows of city blocks along both sides, walls in some gaps, and plain blocks behind."""
    y_front = L.hw + L.sw
    for s in (1, -1):
        lots = _lots(rng, L, 6.0, 20.0, 0.35, (1.0, 4.0))
        for (x0, x1), nxt in zip(lots, lots[1:] + [None]):
            w = x1 - x0
            setback = 0.0 if rng.random() < 0.7 else rng.uniform(0.3, 2.0)
            depth = rng.uniform(10.0, 18.0)
            height = rng.uniform(6.0, 25.0)
            with b.placed(*_side_frame(s, x0 if s > 0 else x1, y_front + setback)):
                A.city_building(b, rng, w, depth, height)
            if nxt is not None and 1.2 < nxt[0] - x1 < 5.0 and rng.random() < 0.4:  # wall or gate across a gap
                kind = "wall" if rng.random() < 0.6 else "panel"
                with b.placed(*_side_frame(s, x1 if s > 0 else nxt[0], y_front + 0.3)):
                    A.fence(b, rng, nxt[0] - x1, kind)
        y_back = y_front + 24.0
        for x0, x1 in _lots(rng, L, 10.0, 30.0, 0.5, (2.0, 8.0), margin=2.0):
            with b.placed(*_side_frame(s, x0 if s > 0 else x1, y_back)):
                A.simple_block(b, rng, x1 - x0, EXTENT - y_back - 1.0, rng.uniform(8.0, 25.0))


def _suburb_rows(b: MeshBuilder, rng: np.random.Generator, L: _Layout) -> int:
    """Houses behind front yards with fences or hedges, garages with cars on driveways, yard trees."""
    y_front = L.hw + L.sw
    cars = 0
    for s in (1, -1):
        lots = _lots(rng, L, 14.0, 24.0, 0.0, (0.0, 0.0), margin=0.5)
        for x0, x1 in lots:
            lot_w = x1 - x0
            hw_ = min(lot_w - 5.0, rng.uniform(8.0, 13.0))
            hd = rng.uniform(7.0, 11.0)
            yard = rng.uniform(3.0, 8.0)
            hx = rng.uniform(1.0, lot_w - hw_ - 4.0)
            with b.placed(*_side_frame(s, x0 if s > 0 else x1, y_front)):
                # the lot, in its own frame: x along the street from the lot's start, y away from it
                with b.placed(0.0, [hx, yard, 0.0]):
                    A.house(b, rng, hw_, hd)
                gx = hx + hw_ + 0.5
                has_garage = gx + 3.5 < lot_w - 0.3 and rng.random() < 0.5
                if has_garage:
                    with b.placed(0.0, [gx, yard + rng.uniform(0.0, 2.0), 0.0]):
                        A.garage(b, rng, 3.5, 6.0)
                drive_x = gx + 1.75 if has_garage else min(hx + hw_ + 2.0, lot_w - 1.5)
                if rng.random() < 0.5 and drive_x + 1.2 < lot_w:
                    shape = A.CAR_SHAPES[int(rng.choice(4, p=[0.3, 0.25, 0.2, 0.25]))]   # no trucks on driveways
                    with b.placed(np.pi / 2 + (0.0 if rng.random() < 0.5 else np.pi), [drive_x, yard * 0.5 + 0.3, 0.0]):
                        A.car(b, rng, shape)
                    cars += 1
                kind = rng.choice(["picket", "hedge", "panel", "wall", "none", "none"], p=[0.3, 0.25, 0.1, 0.05, 0.15, 0.15])
                if kind != "none":  # front fence with a gap for the driveway and one for the path
                    gaps = sorted([(drive_x - 1.6, drive_x + 1.6), (hx + hw_ / 2 - 0.6, hx + hw_ / 2 + 0.6)])
                    cur = 0.2
                    for a, z in gaps + [(lot_w - 0.2, lot_w)]:
                        if a - cur > 0.8:
                            with b.placed(0.0, [cur, 0.2, 0.0]):
                                A.fence(b, rng, a - cur, kind)
                        cur = max(cur, z)
                if rng.random() < 0.6:  # side fence along the lot boundary
                    side_kind = "hedge" if rng.random() < 0.4 else "panel"
                    with b.placed(np.pi / 2, [lot_w - 0.1, yard + 1.0, 0.0]):
                        A.fence(b, rng, rng.uniform(8.0, 20.0), side_kind)
                for _ in range(int(rng.integers(0, 3))):  # yard trees and bushes
                    tx = rng.uniform(1.0, lot_w - 1.0)
                    ty = rng.uniform(yard + hd + 2.0, 28.0) if rng.random() < 0.5 else rng.uniform(1.5, max(1.6, yard - 1.5))
                    if ty < yard and hx - 2.0 < tx < hx + hw_ + 2.0:
                        continue
                    with b.placed(0.0, [tx, ty, 0.0]):
                        A.tree(b, rng, rng.uniform(0.8, 1.3), conifer=rng.random() < 0.3)
                for _ in range(int(rng.integers(0, 4))):
                    tx, ty = rng.uniform(0.8, lot_w - 0.8), rng.uniform(1.2, max(1.3, yard - 0.6))
                    if abs(tx - drive_x) > 2.0:
                        with b.placed(0.0, [tx, ty, 0.0]):
                            A.bush(b, rng)
        y_back = y_front + 32.0
        for x0, x1 in _lots(rng, L, 14.0, 24.0, 0.0, (0.0, 0.0), margin=0.5):
            with b.placed(*_side_frame(s, x0 if s > 0 else x1, y_back)):
                with b.placed(0.0, [rng.uniform(1.0, 3.0), 1.0, 0.0]):
                    A.house(b, rng, min(x1 - x0 - 4.0, rng.uniform(8.0, 12.0)), rng.uniform(7.0, 10.0))
    return cars


def _drive(rng: np.random.Generator, L: _Layout) -> tuple[np.ndarray, int]:
    """Ego sensor path along the right-hand lane with a gentle weave (so headings vary by a degree or two)."""
    direction = 1 if rng.random() < 0.5 else -1
    lane = rng.uniform(1.4, 2.0)
    height = rng.uniform(1.9, 2.1)
    amp, period, phase = rng.uniform(0.0, 0.3), rng.uniform(50.0, 100.0), rng.uniform(0, 2 * np.pi)
    x = np.arange(-EXTENT + 2.0, EXTENT - 2.0 + 1e-9, DRIVE_STEP) * direction
    y = -direction * lane + amp * np.sin(2 * np.pi * x / period + phase)
    return np.c_[x, y, np.full_like(x, height)], direction

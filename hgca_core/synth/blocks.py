"""Building rows along the main street, one builder per scene style.

Positions are street coordinates (see `street.Street`). A lot is addressed in its own frame: lx along the
street from the lot's start, ly away from the street from the sidewalk's back edge; `Lot.at` turns that
into a placement standing on the ground under the object's footprint.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hgca_core.synth import assets as A
from hgca_core.synth import furniture as F
from hgca_core.synth import vehicles as V
from hgca_core.synth.materials import DARK
from hgca_core.synth.primitives import DEFAULT_MATERIAL, MeshBuilder
from hgca_core.synth.street import EXTENT, Street

FENCE_PIECE = 4.0   # long fences are built in pieces that each stand on the ground


@dataclass
class Lot:
    """A lot on side s of the main street spanning u in [x0, x1]; its frame starts at the sidewalk's back."""

    S: Street
    s: int
    x0: float
    x1: float

    @property
    def width(self) -> float:
        return self.x1 - self.x0

    def at(self, lx: float, ly: float, yaw: float = 0.0, foot=(-0.3, -0.3, 0.3, 0.3), lift: float = 0.0,
           tilt: bool = False):
        u = self.x0 + lx if self.s > 0 else self.x1 - lx
        return self.S.side(self.s, u, self.S.hw + self.S.sw + ly, yaw, foot, lift, tilt)

    def fence(self, b: MeshBuilder, rng: np.random.Generator, lx: float, ly: float, length: float, kind: str,
              along_y: bool = False) -> None:
        """A fence of one kind from (lx, ly) along the lot's x (or y), in pieces that follow the ground."""
        seed = int(rng.integers(2**31))
        n = max(1, int(np.ceil(length / FENCE_PIECE)))
        step = length / n
        for k in range(n):
            px, py = (lx, ly + k * step) if along_y else (lx + k * step, ly)
            yaw = np.pi / 2 if along_y else 0.0
            foot = (0.0, 0.0, step, 0.3)
            with b.placed(*self.at(px, py, yaw, foot)):
                F.fence(b, np.random.default_rng(seed), step + (A.OVERLAP if k < n - 1 else 0.0), kind)


def lots(rng: np.random.Generator, S: Street, v0: float, v1: float, wmin: float, wmax: float, gap_p: float,
         gap_range: tuple[float, float], margin: float = 0.0) -> list[tuple[float, float]]:
    """Lots (x0, x1) along a row between distances v0 and v1 from the centre line, skipping the cross street
    (at its angle) with `margin`; gaps between lots with probability gap_p."""
    out, x = [], -EXTENT
    while x < EXTENT - wmin * 0.6:
        w = min(rng.uniform(wmin, wmax), EXTENT - x)
        if S.cross:
            hit = []
            for s in (1, -1):
                lo, hi = S.cross_span(s * v0, s * v1, margin)
                if x + w > lo and x < hi:
                    hit.append(hi)
            if hit:
                x = max(hit) + rng.uniform(0.0, 1.0)
                continue
        out.append((x, x + w))
        # attached neighbours overlap a little, so the party wall lies inside a solid and leaves the truth
        x += w + (rng.uniform(*gap_range) if rng.random() < gap_p else -A.OVERLAP)
    return out


def _front_yard(b: MeshBuilder, rng: np.random.Generator, lot: Lot, depth: float, paths: list[tuple[float, float]],
                kinds=("picket", "hedge", "panel", "wall", "none"), p=(0.3, 0.3, 0.1, 0.15, 0.15)) -> None:
    """A fence or hedge along the front of a yard (gaps for paths and drives), bushes inside."""
    kind = str(rng.choice(kinds, p=p))
    if kind != "none":
        cur = 0.2
        for a, z in sorted(paths) + [(lot.width - 0.2, lot.width)]:
            if a - cur > 0.8:
                lot.fence(b, rng, cur, 0.2, a - cur, kind)
            cur = max(cur, z)
    for _ in range(int(rng.integers(0, 4))):
        tx, ty = rng.uniform(0.8, lot.width - 0.8), rng.uniform(1.2, max(1.3, depth - 0.6))
        if all(abs(tx - (a + z) / 2) > 2.0 for a, z in paths):
            with b.placed(*lot.at(tx, ty)):
                F.bush(b, rng)


def city_rows(b: MeshBuilder, rng: np.random.Generator, S: Street) -> dict:
    """Rows of city blocks along both sides (towers, set-back apartments behind front yards, dark cladding),
    walls in some gaps, and plain blocks behind."""
    y_front = S.hw + S.sw
    towers = 0
    for s in (1, -1):
        row = lots(rng, S, y_front, y_front + 20.0, 6.0, 20.0, 0.35, (1.0, 4.0))
        for (x0, x1), nxt in zip(row, row[1:] + [None]):
            lot = Lot(S, s, x0, x1)
            w, depth = x1 - x0, rng.uniform(10.0, 18.0)
            kind = rng.random()
            setback = 0.0 if kind < 0.6 else rng.uniform(0.3, 2.0) if kind < 0.82 else rng.uniform(3.0, 7.0)
            tall = rng.random() < 0.15
            towers += int(tall)
            height = rng.uniform(25.0, 45.0) if tall else rng.uniform(6.0, 25.0)
            with b.material(DARK if rng.random() < 0.1 else DEFAULT_MATERIAL):
                with b.placed(*lot.at(0.0, setback, foot=(0, 0, w, depth))):
                    A.city_building(b, rng, w, depth, height)
            if setback > 3.0:   # an apartment block behind a front yard
                _front_yard(b, rng, lot, setback, [(w / 2 - 1.0, w / 2 + 1.0)], ("hedge", "wall", "panel", "none"),
                            (0.45, 0.25, 0.15, 0.15))
            if nxt is not None and 1.2 < nxt[0] - x1 < 5.0 and rng.random() < 0.4:  # wall or gate across a gap
                gap = Lot(S, s, x1, nxt[0])
                gap.fence(b, rng, 0.0, 0.3, nxt[0] - x1, "wall" if rng.random() < 0.6 else "panel")
        _back_row(b, rng, S, s, y_front + 24.0, lambda w: rng.uniform(8.0, 25.0))
    return {"towers": towers}


def _back_row(b: MeshBuilder, rng: np.random.Generator, S: Street, s: int, v: float, height) -> None:
    for x0, x1 in lots(rng, S, v, EXTENT, 10.0, 30.0, 0.5, (2.0, 8.0), margin=2.0):
        lot = Lot(S, s, x0, x1)
        depth = EXTENT - v - 1.0
        with b.placed(*lot.at(0.0, v - S.hw - S.sw, foot=(0, 0, x1 - x0, depth))):
            if rng.random() < 0.25:
                A.warehouse(b, rng, x1 - x0, depth)
            else:
                A.simple_block(b, rng, x1 - x0, depth, height(x1 - x0))


def suburb_rows(b: MeshBuilder, rng: np.random.Generator, S: Street) -> dict:
    """Houses behind front yards with fences or hedges, garages with cars on driveways, yard trees."""
    y_front = S.hw + S.sw
    cars = 0
    for s in (1, -1):
        for x0, x1 in lots(rng, S, y_front, y_front + 30.0, 14.0, 24.0, 0.0, (0.0, 0.0), margin=0.5):
            lot = Lot(S, s, x0, x1)
            lot_w = lot.width
            hw_ = min(lot_w - 5.0, rng.uniform(8.0, 13.0))
            hd = rng.uniform(7.0, 11.0)
            yard = rng.uniform(3.0, 8.0)
            hx = rng.uniform(1.0, lot_w - hw_ - 4.0)
            with b.placed(*lot.at(hx, yard, foot=(0, 0, hw_, hd))):
                A.house(b, rng, hw_, hd)
            gx = hx + hw_ + 0.5
            has_garage = gx + 3.5 < lot_w - 0.3 and rng.random() < 0.5
            if has_garage:
                gy = yard + rng.uniform(0.0, 2.0)
                with b.placed(*lot.at(gx, gy, foot=(0, 0, 3.5, 6.0))):
                    A.garage(b, rng, 3.5, 6.0)
            drive_x = gx + 1.75 if has_garage else min(hx + hw_ + 2.0, lot_w - 1.5)
            if rng.random() < 0.5 and drive_x + 1.2 < lot_w:
                yaw = np.pi / 2 + (0.0 if rng.random() < 0.5 else np.pi)
                with b.placed(*lot.at(drive_x, yard * 0.5 + 0.3, yaw, foot=(-2.3, -1.0, 2.3, 1.0), tilt=True)):
                    V.vehicle(b, rng, V.pick_shape(rng, big=False))
                cars += 1
            _front_yard(b, rng, lot, yard, [(drive_x - 1.6, drive_x + 1.6), (hx + hw_ / 2 - 0.6, hx + hw_ / 2 + 0.6)])
            if rng.random() < 0.6:  # side fence along the lot boundary
                lot.fence(b, rng, lot_w - 0.1, yard + 1.0, rng.uniform(8.0, 20.0),
                          "hedge" if rng.random() < 0.4 else "panel", along_y=True)
            for _ in range(int(rng.integers(0, 3))):  # yard trees
                tx = rng.uniform(1.0, lot_w - 1.0)
                ty = rng.uniform(yard + hd + 2.0, 28.0) if rng.random() < 0.5 else rng.uniform(1.5, max(1.6, yard - 1.5))
                if ty < yard and hx - 2.0 < tx < hx + hw_ + 2.0:
                    continue
                with b.placed(*lot.at(tx, ty)):
                    F.tree(b, rng, rng.uniform(0.8, 1.3), conifer=rng.random() < 0.3)
        for x0, x1 in lots(rng, S, y_front + 32.0, EXTENT, 14.0, 24.0, 0.0, (0.0, 0.0), margin=0.5):
            lot = Lot(S, s, x0, x1)
            w, d = min(x1 - x0 - 4.0, rng.uniform(8.0, 12.0)), rng.uniform(7.0, 10.0)
            with b.placed(*lot.at(rng.uniform(1.0, 3.0), 33.0, foot=(0, 0, w, d))):
                A.house(b, rng, w, d)
    return {"driveway_cars": cars}


def town_rows(b: MeshBuilder, rng: np.random.Generator, S: Street) -> dict:
    """Terraced houses behind small front gardens (low walls, hedges, railings), small shops and warehouses."""
    y_front = S.hw + S.sw
    terraces = 0
    for s in (1, -1):
        for x0, x1 in lots(rng, S, y_front, y_front + 16.0, 18.0, 45.0, 0.5, (1.5, 6.0)):
            kind = rng.choice(["terrace", "shop", "warehouse"], p=[0.6, 0.25, 0.15])
            if kind == "warehouse":
                with b.placed(*Lot(S, s, x0, x1).at(0.0, rng.uniform(0.0, 6.0), foot=(0, 0, x1 - x0, 15.0))):
                    A.warehouse(b, rng, x1 - x0, rng.uniform(12.0, 15.0))
                continue
            if kind == "shop":
                w = x1 - x0
                with b.placed(*Lot(S, s, x0, x1).at(0.0, 0.0, foot=(0, 0, w, 12.0))):
                    A.city_building(b, rng, w, rng.uniform(9.0, 12.0), rng.uniform(6.5, 11.0))
                continue
            terraces += 1
            garden, depth = rng.uniform(1.5, 4.5), rng.uniform(8.0, 11.0)
            storeys = int(rng.integers(2, 4))
            x = x0
            while x < x1 - 4.0:
                w = min(rng.uniform(5.0, 8.0), x1 - x)
                lot = Lot(S, s, x, x + w)
                with b.placed(*lot.at(0.0, garden, foot=(0, 0, w, depth))):
                    A.row_house(b, rng, w + A.OVERLAP, depth, storeys)
                _front_yard(b, rng, lot, garden, [(w * 0.3 - 0.2, w * 0.3 + 1.4)], ("wall", "hedge", "picket", "none"),
                            (0.4, 0.3, 0.15, 0.15))
                x += w
        _back_row(b, rng, S, s, y_front + 22.0, lambda w: rng.uniform(6.0, 14.0))
    return {"terraces": terraces}


def _shop_units(b: MeshBuilder, rng: np.random.Generator, S: Street, s: int, x0: float, x1: float, ly: float) -> None:
    """A row of single-storey shop units (5-12 m each) standing `ly` behind the sidewalk, flush or stepped."""
    x = x0
    while x < x1 - 3.0:
        w = min(rng.uniform(5.0, 12.0), x1 - x)
        lot = Lot(S, s, x, x + w)
        step = rng.uniform(0.0, 0.8) if rng.random() < 0.3 else 0.0
        with b.material(DARK if rng.random() < 0.1 else DEFAULT_MATERIAL):
            with b.placed(*lot.at(0.0, ly + step, foot=(0, 0, w, 12.0))):
                A.low_shop(b, rng, w + A.OVERLAP, rng.uniform(9.0, 14.0))
        x += w


def _car_rows(b: MeshBuilder, rng: np.random.Generator, lot: Lot, ly0: float, ly1: float) -> int:
    """Cars parked nose-in in rows across a parking lot between ly0 and ly1 (5.5 m rows, 7 m aisles)."""
    cars, ly = 0, ly0 + 2.6
    while ly + 2.5 < ly1:
        for lx in np.arange(1.6, lot.width - 1.4, 2.6):
            if rng.random() < 0.55:
                yaw = np.pi / 2 + (0.0 if rng.random() < 0.5 else np.pi) + np.radians(rng.normal(0.0, 3.0))
                with b.placed(*lot.at(lx, ly, yaw, foot=(-1.0, -2.3, 1.0, 2.3), tilt=True)):
                    V.vehicle(b, rng, V.pick_shape(rng, big=False))
                cars += 1
        ly += 12.5
    return cars


def strip_rows(b: MeshBuilder, rng: np.random.Generator, S: Street) -> dict:
    """Low-rise commercial strips (most real streets): single-storey shops, parking lots in front of
    set-back shops, open lots behind walls or fences, low halls; above 5 m mostly sky, trees and poles."""
    y_front = S.hw + S.sw
    counts = {"low_shops": 0, "parking_cars": 0, "open_lots": 0}
    for s in (1, -1):
        for x0, x1 in lots(rng, S, y_front, y_front + 30.0, 10.0, 40.0, 0.3, (2.0, 10.0), margin=0.5):
            lot = Lot(S, s, x0, x1)
            kind = str(rng.choice(["shops", "parking", "open", "hall"], p=[0.4, 0.3, 0.15, 0.15]))
            if kind == "shops":
                counts["low_shops"] += 1
                _shop_units(b, rng, S, s, x0, x1, rng.uniform(0.0, 1.5))
            elif kind == "parking":
                back = rng.uniform(14.0, 24.0)
                counts["parking_cars"] += _car_rows(b, rng, lot, 0.5, back - 1.0)
                if rng.random() < 0.7:
                    _shop_units(b, rng, S, s, x0, x1, back)
                if rng.random() < 0.5:  # a low wall, hedge or rail along the front, a gap for the entrance
                    kind_f = str(rng.choice(["hedge", "wall", "picket"]))
                    gate = rng.uniform(1.0, max(1.1, lot.width - 7.0))
                    for a, z in ((0.2, gate), (gate + 6.0, lot.width - 0.2)):
                        if z - a > 1.0:
                            lot.fence(b, rng, a, 0.2, z - a, kind_f)
                for _ in range(int(rng.integers(0, 3))):   # lamps in the lot
                    with b.placed(*lot.at(rng.uniform(1.0, lot.width - 1.0), rng.uniform(2.0, back - 2.0))):
                        F.street_lamp(b, rng)
            elif kind == "open":
                counts["open_lots"] += 1
                lot.fence(b, rng, 0.2, 0.3, lot.width - 0.4, "wall" if rng.random() < 0.5 else "panel")
                for _ in range(int(rng.integers(0, 4))):
                    with b.placed(*lot.at(rng.uniform(1.0, lot.width - 1.0), rng.uniform(2.0, 25.0))):
                        F.bush(b, rng) if rng.random() < 0.6 else F.tree(b, rng, rng.uniform(0.7, 1.2))
            else:
                setback = rng.uniform(0.0, 8.0)
                with b.placed(*lot.at(0.0, setback, foot=(0, 0, lot.width, 15.0))):
                    A.warehouse(b, rng, lot.width, rng.uniform(12.0, 20.0), heights=(3.8, 6.5))
            if rng.random() < 0.4:  # trees at the lot's edge
                with b.placed(*lot.at(rng.uniform(0.5, lot.width - 0.5), rng.uniform(0.6, 1.2))):
                    F.tree(b, rng, rng.uniform(0.7, 1.2), conifer=rng.random() < 0.2)
        if rng.random() < 0.6:  # some of the back row, low
            _back_row(b, rng, S, s, y_front + 34.0, lambda w: rng.uniform(3.5, 8.0))
    return counts

"""Street scene layout: a main street through a 120 x 120 m block, seeded.

The layout is written in street coordinates (u along the main street, v across it, +v on the north
side) and bent onto the world by the street's centre line (straight or a gentle arc); the ground is a
height field (flat, a grade, or rolling hills, with a cambered road), and every object stands on the
ground under its footprint. A cross street may meet the main street at an angle. Styles: "city" (dense
rows of 6-45 m blocks, shops with glass fronts and awnings, apartments behind front yards), "suburb"
(gabled houses set back behind yards, fences and hedges, garages and driveways, many trees), "town"
(terraced houses behind small front gardens, small shops, warehouses) and "strip" (low-rise commercial:
single-storey shops, parking lots, open lots behind walls, low halls).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from hgca_core.synth import furniture as F
from hgca_core.synth import vehicles as V
from hgca_core.synth.assets import ROAD, SIDEWALK
from hgca_core.synth.blocks import city_rows, strip_rows, suburb_rows, town_rows
from hgca_core.synth.materials import resolve
from hgca_core.synth.primitives import MeshBuilder, Solids
from hgca_core.synth.street import EXTENT, Street
from hgca_core.synth.terrain import StreetCurve, Terrain, make_terrain

STYLES = ("city", "suburb", "town", "strip")
STYLE_P = (0.3, 0.25, 0.15, 0.3)
# The seed's style draw of each generator version (`dataset.GENERATOR_VERSION`): version 7 added "strip"; with
# the draw of version 6 every seed gives its version-6 scene again, so data built by it (synth2, the val and
# test splits of the earlier tables) can be rebuilt exactly.
STYLE_DRAWS = {6: (STYLES[:3], (0.45, 0.35, 0.2)), 7: (STYLES, STYLE_P)}
GENERATOR_VERSION = max(STYLE_DRAWS)   # bumped whenever the same seed would produce different content
GROUND_HALF = 78.0  # the ground reaches further, so a bent layout still stands on it
DRIVE_STEP = 0.5    # spacing of drive samples (metres)
BLOCK = 40.0        # street stretch over which parked cars are counted (metres)
PIECE = 3.0         # sidewalks follow the ground in pieces this long


@dataclass
class StreetScene:
    """A generated scene. `drive` is the ego vehicle path on the road surface (M, 3) with the ground's up
    vector there (`drive_up`); `street_half_width` the main street corridor (road + sidewalks) either side
    of the centre line; `solids` the volumes whose interior holds no visible surface; `terrain` the ground
    and `curve` the centre line (street coordinates <-> world)."""

    mesh: trimesh.Trimesh
    face_labels: np.ndarray
    face_materials: np.ndarray
    drive: np.ndarray
    drive_up: np.ndarray
    street_half_width: float
    style: str
    seed: int
    solids: Solids
    terrain: Terrain
    curve: StreetCurve
    layout: dict = field(default_factory=dict)
    ground_faces: int = 0     # the mesh's first faces are the terrain's

    def corridor(self, step: float = 0.5) -> np.ndarray:
        """(2, M, 2) world x, y of the corridor's two edges (v = -/+ half width), every `step` metres of u."""
        u = np.arange(-EXTENT, EXTENT + 1e-9, step)
        return np.stack([self.curve.to_world(u, s * self.street_half_width) for s in (-1.0, 1.0)])


def make_scene(seed: int, style: str | None = None, generator: int = GENERATOR_VERSION) -> StreetScene:
    """The scene named by `seed` (and `style`; by default the seed picks it) as generator version `generator`
    made it."""
    if generator not in STYLE_DRAWS:
        raise ValueError(f"unknown generator version {generator!r}; use one of {', '.join(map(str, STYLE_DRAWS))}")
    styles, p = STYLE_DRAWS[generator]
    rng = np.random.default_rng([int(seed), 7919])
    picked = styles[int(rng.choice(len(styles), p=p))]
    style = picked if style is None else style
    if style not in styles:
        raise ValueError(f"unknown style {style!r} for generator version {generator}; use one of {', '.join(styles)}")
    city, suburb = style == "city", style == "suburb"
    hw = rng.uniform(5.5, 8.0) if city else rng.uniform(4.5, 6.0)
    curve = StreetCurve(0.0 if rng.random() < 0.45 else rng.uniform(1 / 700, 1 / 220) * rng.choice([-1, 1]))
    terrain, ground = make_terrain(rng, GROUND_HALF, curve, hw)
    S = Street(hw=hw, sw=rng.uniform(2.5, 5.0) if city else rng.uniform(1.8, 3.0), hs=rng.uniform(0.11, 0.14),
               cross=rng.random() < (0.6 if city else 0.45), xc=rng.uniform(-25.0, 25.0),
               hw2=rng.uniform(4.0, 6.5) if city else rng.uniform(3.5, 5.0),
               theta=np.radians(90.0 if rng.random() < 0.4 else rng.uniform(55.0, 125.0)), curve=curve, terrain=terrain)
    b = MeshBuilder()
    b.add(*terrain.mesh_arrays(), ROAD)
    _sidewalks(b, S)
    blocked = _street_furniture(b, rng, S, style)
    parked = _parked_vehicles(b, rng, S, blocked, city)
    extra = {"city": city_rows, "suburb": suburb_rows, "town": town_rows, "strip": strip_rows}[style](b, rng, S)
    _people_and_bikes(b, rng, S, style)
    mesh, labels, solids = b.build()
    materials = resolve(b.materials, labels)
    drive, up, direction = _drive(rng, S)
    layout = {"road_half_width": S.hw, "sidewalk_width": S.sw, "sidewalk_height": S.hs,
              "crossroad_x": S.xc if S.cross else None, "crossroad_half_width": S.hw2 if S.cross else None,
              "crossroad_angle_deg": round(float(np.degrees(S.theta)), 1) if S.cross else None,
              "curvature": round(float(curve.k), 5), "ground": ground, "parked_cars": parked,
              "drive_direction": direction, "faces": int(len(mesh.faces)), **extra}
    return StreetScene(mesh, labels, materials, drive, up, S.hw + S.sw, style, int(seed), solids, terrain, curve,
                       layout, int(len(terrain.mesh_arrays()[1])))


def slab(b: MeshBuilder, S: Street, quad_uv, label: int, lift: float, piece: float = PIECE) -> None:
    """A raised slab on the ground (sidewalk) over the street-coordinate quad (p00, p10, p01, p11), cut into
    pieces along p00 -> p10 that each follow the ground: tops `lift` above it, bottoms below it."""
    p00, p10, p01, p11 = (np.asarray(p, dtype=np.float64) for p in quad_uv)
    n = max(1, int(np.ceil(max(np.linalg.norm(p10 - p00), np.linalg.norm(p11 - p01)) / piece)))
    t = np.linspace(0.0, 1.0, n + 1)
    near, far = p00 + t[:, None] * (p10 - p00), p01 + t[:, None] * (p11 - p01)
    xy_near, xy_far = S.curve.to_world(near[:, 0], near[:, 1]), S.curve.to_world(far[:, 0], far[:, 1])
    e1, e2 = xy_near[-1] - xy_near[0], xy_far[0] - xy_near[0]
    if e1[0] * e2[1] - e1[1] * e2[0] < 0:                            # keep the box right-handed (outward faces)
        xy_near, xy_far = xy_far, xy_near
    zn, zf = S.terrain.height(xy_near), S.terrain.height(xy_far)
    for k in range(n):
        c = []
        for top in (False, True):
            for xy, z in ((xy_near, zn), (xy_far, zf)):
                for i in (k, k + 1):
                    c.append([xy[i, 0], xy[i, 1], z[i] + lift if top else z[i] - 0.1])
        skip = ("-z",) + (() if k == 0 else ("-x",)) + (() if k == n - 1 else ("+x",))
        b.hexahedron(np.array(c), label, skip=skip)


def _sidewalks(b: MeshBuilder, S: Street) -> None:
    """Raised sidewalks with curbs along the main street (cut by the cross street at its angle) and along
    the cross street."""
    for s in (1, -1):
        v_in, v_out = s * S.hw, s * (S.hw + S.sw)
        if S.cross:
            off = S.hw2 / np.sin(S.theta)
            spans = [((-EXTENT, -EXTENT), (S.cross_u(v_in) - off, S.cross_u(v_out) - off)),
                     ((S.cross_u(v_in) + off, S.cross_u(v_out) + off), (EXTENT, EXTENT))]
        else:
            spans = [((-EXTENT, -EXTENT), (EXTENT, EXTENT))]
        for (a_in, a_out), (z_in, z_out) in spans:
            slab(b, S, [(a_in, v_in), (z_in, v_in), (a_out, v_out), (z_out, v_out)], SIDEWALK, S.hs)
    if S.cross:
        sn = np.sin(S.theta)
        for s in (1, -1):
            va, vb = s * (S.hw + S.sw - 0.05), s * EXTENT
            for d0, d1 in ((S.hw2, S.hw2 + S.sw), (-S.hw2 - S.sw, -S.hw2)):
                quad = [(S.cross_u(v) + d / sn, v) for v in (va, vb) for d in (d0, d1)]
                slab(b, S, [quad[0], quad[2], quad[1], quad[3]], SIDEWALK, S.hs)


def _street_furniture(b: MeshBuilder, rng: np.random.Generator, S: Street, style: str) -> list[tuple[int, float, float]]:
    """Lamps, street trees, signs, a bus shelter, benches, bins, bollards, utility poles, traffic lights.
    Returns (side, u0, u1) spans at the curb that parked cars must leave free (bus stops)."""
    city, suburb = style == "city", style == "suburb"
    blocked: list[tuple[int, float, float]] = []
    z = S.hs
    if rng.random() < (0.6 if city else 0.3):  # bus shelter, against the back of the sidewalk
        s = int(rng.choice([-1, 1]))
        for _ in range(10):
            x = rng.uniform(-45, 40)
            if S.x_free(x, 2.0) and S.x_free(x + 5, 2.0):
                break
        with b.placed(*S.side(s, x, S.hw + max(0.6, S.sw - 1.9), foot=(0, 0, 5, 1.8), lift=z)):
            length = F.bus_shelter(b, rng)
        blocked.append((s, x - 6.0, x + length + 6.0) if s > 0 else (s, x - length - 6.0, x + 6.0))
    for s in (1, -1):
        occupied: list[float] = []

        def put(u: float, v: float, make, *args, foot=(-0.3, -0.3, 0.3, 0.3)) -> None:
            with b.placed(*S.side(s, u, v, foot=foot, lift=z)):
                make(b, rng, *args)
            occupied.append(u)

        if rng.random() < 0.85:  # street lamps near the curb
            step = rng.uniform(18.0, 30.0)
            for x in np.arange(-EXTENT + rng.uniform(2, step), EXTENT - 2, step):
                if S.x_free(x, 0.5):
                    put(x, S.hw + 0.45, F.street_lamp)
        if rng.random() < (0.55 if city else 0.7):  # a row of street trees
            step = rng.uniform(7.0, 13.0)
            scale = rng.uniform(0.8, 1.2)
            for x in np.arange(-EXTENT + rng.uniform(2, step), EXTENT - 2, step):
                if S.x_free(x, 1.5) and all(abs(x - o) > 2.0 for o in occupied) and rng.random() < 0.9:
                    put(x, S.hw + min(1.2, S.sw / 2), F.tree, scale)
        if not city and rng.random() < 0.5:  # wooden utility poles
            step = rng.uniform(30.0, 45.0)
            for x in np.arange(-EXTENT + rng.uniform(2, step), EXTENT - 2, step):
                if S.x_free(x, 0.5) and all(abs(x - o) > 1.5 for o in occupied):
                    put(x, S.hw + S.sw - 0.4, F.utility_pole)
        for _ in range(int(rng.integers(1, 5))):  # sign poles
            x = rng.uniform(-EXTENT + 2, EXTENT - 2)
            if S.x_free(x, 0.5) and all(abs(x - o) > 1.5 for o in occupied):
                put(x, S.hw + 0.35, F.sign_pole)
        if not suburb:
            for _ in range(int(rng.integers(0, 5))):
                x = rng.uniform(-EXTENT + 2, EXTENT - 2)
                if not S.x_free(x, 0.5) or any(abs(x - o) < 2.5 for o in occupied):
                    continue
                kind = int(rng.integers(0, 3))
                if kind == 2:  # a row of bollards along the curb
                    for k in range(int(rng.integers(2, 6))):
                        put(x + 1.5 * k, S.hw + 0.4, F.bollard)
                else:
                    put(x, S.hw + S.sw * 0.6, (F.bench, F.trash_bin)[kind], foot=(-1.1, 0, 1.1, 0.45))
    if S.cross and not suburb and rng.random() < 0.7:  # traffic lights on the corners, arms over the main road
        for sx in (-1, 1):
            for s in (-1, 1):
                if rng.random() < 0.75:
                    v = S.hw + 0.5
                    u = S.cross_u(s * v) + sx * (S.hw2 + 0.5) / np.sin(S.theta)
                    with b.placed(*S.side(s, u, v, lift=z)):
                        F.traffic_light(b, rng)
    return blocked


def free_position(rng: np.random.Generator, lo: float, hi: float, length: float, taken: list[tuple[float, float]],
                  gap: float) -> float | None:
    """A uniform centre for an interval of `length` in [lo, hi]; if it collides, moved to the nearest free
    spot (the paper moves colliding cars). None when nothing is free."""
    half = length / 2 + gap
    if hi - lo < 2 * half:
        return None
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


def _parked_vehicles(b: MeshBuilder, rng: np.random.Generator, S: Street, blocked: list[tuple[int, float, float]],
                     city: bool) -> list[dict]:
    """Vehicles parked at both curbs of the main street, never overlapping: cars, vans, trucks, buses and
    motorbikes. As in Karton City, the count per side of a street stretch is Poisson(2), at most 7; our
    stretch is one 40 m block (a region's length), so a sample sees about as many cars as a Karton City one."""
    out = []
    for s in (1, -1):
        taken: list[tuple[float, float]] = [(x0, x1) for side, x0, x1 in blocked if side == s]
        if S.cross:
            taken.append(S.cross_span(s * (S.hw - 2.5), s * S.hw, 4.0, width=S.hw2))
        for x_lo in np.arange(-EXTENT, EXTENT - 1.0, BLOCK):
            for _ in range(min(int(rng.poisson(2.0)), 7)):
                moto = rng.random() < 0.08
                shape = "motorbike" if moto else V.pick_shape(rng)
                length = 2.2 if moto else V.LENGTH_MAX[shape]
                x = free_position(rng, max(x_lo, -EXTENT + 1), min(x_lo + BLOCK, EXTENT - 1), length, taken, 0.6)
                if x is None:
                    continue
                taken.append((x - length / 2, x + length / 2))
                y = s * (S.hw - (0.6 if moto else 1.0) - rng.uniform(0.15, 0.4)
                         - (0.25 if shape in ("truck", "bus") else 0.0))
                yaw = (0.0 if rng.random() < 0.5 else np.pi) + np.radians(rng.normal(0.0, 1.5))
                with b.placed(*S.place(x, y, yaw, (-length / 2, -1.25, length / 2, 1.25), tilt=True)):
                    if moto:
                        V.motorbike(b, rng)
                    else:
                        V.vehicle(b, rng, shape)
                out.append({"shape": shape, "x": round(float(x), 2), "y": round(float(y), 2),
                            "yaw_deg": round(float(np.degrees(yaw)), 1)})
    if S.cross and city:  # a few on the cross street too
        sn = np.sin(S.theta)
        for sx in (-1, 1):
            for _ in range(min(int(rng.poisson(1.0)), 3)):
                v = rng.uniform(S.hw + S.sw + 4, EXTENT - 4) * rng.choice([-1, 1])
                u = S.cross_u(v) + sx * (S.hw2 - 1.2) / sn
                with b.placed(*S.place(u, v, S.theta + (0.0 if rng.random() < 0.5 else np.pi), (-2.5, -1.0, 2.5, 1.0),
                                       tilt=True)):
                    V.vehicle(b, rng, V.pick_shape(rng, big=False))
    return out


def _people_and_bikes(b: MeshBuilder, rng: np.random.Generator, S: Street, style: str) -> None:
    """People standing on the sidewalks (alone or in small groups) and bicycle racks."""
    n = {"city": (3, 12), "town": (2, 8), "suburb": (0, 4), "strip": (1, 6)}[style]
    for _ in range(int(rng.integers(*n))):
        s = int(rng.choice([-1, 1]))
        u = rng.uniform(-EXTENT + 3, EXTENT - 3)
        if not S.x_free(u, 1.0):
            continue
        v = S.hw + rng.uniform(0.6, S.sw - 0.4)
        for k in range(1 if rng.random() < 0.6 else int(rng.integers(2, 4))):
            with b.placed(*S.side(s, u + 0.7 * k, v + rng.normal(0, 0.2), rng.uniform(0, 2 * np.pi),
                                  lift=S.hs)):
                F.person(b, rng)
    if style != "suburb":
        for s in (1, -1):
            if rng.random() < 0.4 and S.sw > 2.2:
                u = rng.uniform(-EXTENT + 5, EXTENT - 10)
                if S.x_free(u - 5.0, 1.0) and S.x_free(u, 1.0) and S.x_free(u + 5.0, 1.0):
                    with b.placed(*S.side(s, u, S.hw + S.sw - 1.0, foot=(0, -0.9, 5, 0.9), lift=S.hs)):
                        F.bike_rack(b, rng, V.bicycle)


def _drive(rng: np.random.Generator, S: Street) -> tuple[np.ndarray, np.ndarray, int]:
    """Ego vehicle path on the road along the right-hand lane with a gentle weave (headings vary by a degree
    or two), and the ground's up vector under it (the vehicle pitches and rolls with the road)."""
    direction = 1 if rng.random() < 0.5 else -1
    lane = rng.uniform(1.4, 2.0)
    amp, period, phase = rng.uniform(0.0, 0.3), rng.uniform(50.0, 100.0), rng.uniform(0, 2 * np.pi)
    u = np.arange(-EXTENT + 2.0, EXTENT - 2.0 + 1e-9, DRIVE_STEP) * direction
    v = -direction * lane + amp * np.sin(2 * np.pi * u / period + phase)
    xy = S.curve.to_world(u, v)
    return np.c_[xy, S.terrain.height(xy)], S.terrain.up(xy), direction

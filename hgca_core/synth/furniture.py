"""Street objects for the scenes, each in its own frame standing on z = 0: trees with porous crowns and
bushes, lamps, signs, traffic lights, bollards, benches, bins, bus shelters, bicycle racks, fences and
hedges, and people standing still.
"""
from __future__ import annotations

import numpy as np

from hgca_core.synth.assets import FENCE, OVERLAP, PERSON, POLE, SHELTER, TREE
from hgca_core.synth.materials import BARK, DARK, FABRIC, FOLIAGE, GLASS, RETRO
from hgca_core.synth.primitives import MeshBuilder


def tree(b: MeshBuilder, rng: np.random.Generator, scale: float = 1.0, conifer: bool = False) -> float:
    """Trunk plus a canopy of clustered blobs (or stacked cones for a conifer); returns the canopy radius."""
    trunk_h = rng.uniform(1.8, 3.2) * scale
    r_trunk = rng.uniform(0.12, 0.25) * scale
    if conifer:
        h = rng.uniform(5.0, 10.0) * scale
        base = rng.uniform(1.5, 2.5) * scale
        with b.material(BARK):
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
    with b.material(BARK):
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
    """One to three overlapping leafy blobs (porous like crowns)."""
    r = rng.uniform(0.5, 1.1)
    b.ellipsoid([0, 0, r * 0.7], r, r * 0.7, TREE)
    for _ in range(int(rng.integers(0, 3))):
        ang, rr = rng.uniform(0, 2 * np.pi), r * rng.uniform(0.5, 0.8)
        b.ellipsoid([0.7 * r * np.cos(ang), 0.7 * r * np.sin(ang), rr * 0.7], rr, rr * 0.75, TREE)


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
    with b.material(RETRO):
        b.box([-s / 2, -0.08, h - s], [s / 2, -0.04, h], POLE, skip=())


def traffic_light(b: MeshBuilder, rng: np.random.Generator) -> None:
    h = rng.uniform(3.5, 5.5)
    b.cylinder([0, 0, 0], [0, 0, h], 0.1, POLE, segments=8)
    arm = rng.uniform(2.0, 4.0)
    b.box([-0.06, -arm, h - 0.15], [0.06, 0.05, h], POLE, skip=())
    b.box([-0.18, -arm, h - 1.1], [0.18, -arm + 0.3, h - 0.1], POLE, skip=())
    b.box([-0.18, 0.1, 2.0], [0.18, 0.4, 2.9], POLE, skip=())


def utility_pole(b: MeshBuilder, rng: np.random.Generator) -> None:
    """Wooden pole with a cross arm and insulators, 8.5-11 m tall."""
    h = rng.uniform(8.5, 11.0)
    with b.material(BARK):
        b.cylinder([0, 0, 0], [0, 0, h], rng.uniform(0.12, 0.16), POLE, segments=8, radius_top=0.1)
        b.box([-0.06, -0.9, h - 0.8], [0.06, 0.9, h - 0.65], POLE, skip=())
    for y in (-0.75, 0.0, 0.75):
        b.cylinder([0, y, h - 0.65], [0, y, h - 0.45], 0.04, POLE, segments=6)


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
    with b.material(GLASS):                                   # glass back and side panes
        b.box([0.05, D - 0.06, 0.1], [L - 0.05, D, h + OVERLAP], SHELTER, skip=())
        for x0 in (0.0, L - 0.05):
            b.box([x0, D * 0.35, 0.1], [x0 + 0.05, D - 0.06 + OVERLAP, h + OVERLAP], SHELTER, skip=())
    for x0 in (0.0, L - 0.05):
        with b.material(DARK):
            b.box([x0, D - 0.06, 0.0], [x0 + 0.08, D, h + OVERLAP], SHELTER, skip=("-z", "+z"))
    b.box([0.5, D - 0.5, 0.42], [L - 0.5, D - 0.06 + OVERLAP, 0.48], SHELTER, skip=())
    return L


def fence(b: MeshBuilder, rng: np.random.Generator, length: float, kind: str) -> None:
    """Fence along x from 0 to length: 'picket' (posts and rails), 'panel', 'wall' or 'hedge'."""
    if kind == "hedge":
        t, h = rng.uniform(0.6, 1.0), rng.uniform(1.0, 1.8)
        with b.material(FOLIAGE):
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


def bike_rack(b: MeshBuilder, rng: np.random.Generator, bikes) -> float:
    """Hoops along x with bicycles standing in some of them (`bikes(b, rng)` builds one); returns the length."""
    n = int(rng.integers(3, 7))
    for i in range(n):
        x = i * 0.8
        b.cylinder([x, 0, 0], [x, 0, 0.8], 0.025, POLE, segments=6)
        b.cylinder([x + 0.5, 0, 0], [x + 0.5, 0, 0.8], 0.025, POLE, segments=6)
        b.box([x, -0.025, 0.8 - OVERLAP], [x + 0.5, 0.025, 0.85], POLE, skip=())
        if rng.random() < 0.6:
            with b.placed(np.pi / 2 + rng.normal(0, 0.05), [x + 0.25 + 0.25, 0.0, 0.0]):
                bikes(b, rng)
    return n * 0.8


def person(b: MeshBuilder, rng: np.random.Generator) -> None:
    """A person standing still, facing +x: legs, torso, arms, head (1.5 to 1.95 m tall)."""
    h = rng.uniform(1.5, 1.95)
    leg, torso = 0.47 * h, 0.3 * h
    w = rng.uniform(0.36, 0.46)
    with b.material(FABRIC if rng.random() < 0.6 else DARK):
        for y in (-0.1, 0.1):
            b.cylinder([0, y * w / 0.4, 0], [0, y * w / 0.4, leg + OVERLAP], 0.075, PERSON, segments=8)
        b.box([-0.12, -w / 2, leg], [0.12, w / 2, leg + torso], PERSON)
        for y in (-1, 1):
            b.cylinder([0, y * (w / 2 + 0.05), leg + torso - 0.03], [0.03, y * (w / 2 + 0.08), leg + 0.05], 0.045,
                       PERSON, segments=6)
        b.cylinder([0, 0, leg + torso - OVERLAP], [0, 0, leg + torso + 0.07], 0.05, PERSON, segments=6)
    b.ellipsoid([0, 0, h - 0.11], 0.095, 0.12, PERSON)

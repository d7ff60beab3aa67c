"""Sensor profiles and real-sensor effects: beam tables against the real sweeps, and each effect doing what
it says (and nothing when switched off)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import trimesh

from hgca_core.geometry.raycast import make_intersector
from hgca_core.synth.lidar import (AV2_DOWN_IN_RIG, AV2_UP_HEIGHT, HDL32E, NO_EFFECTS, PROFILES, VLP32C, Effects, Unit,
                                   detection_probability, scan)
from hgca_core.synth.materials import DARK, DIFFUSE, FOLIAGE, GLASS, WINDOW
from real_sweeps import av2_sweeps, elevations, nuscenes_sweep


def _vehicle(x=0.0, y=0.0, yaw=0.0) -> np.ndarray:
    m = np.eye(4)
    m[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    m[:2, 3] = [x, y]
    return m


def _ground(half: float = 150.0) -> trimesh.Trimesh:
    v = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], dtype=float)
    return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)


def _walls(*xs: float, size: float = 60.0) -> tuple[trimesh.Trimesh, list[slice]]:
    """Thin walls facing the sensor at x = xs (each 12 faces), in that order."""
    parts = []
    for x in xs:
        w = trimesh.creation.box(extents=[0.02, size, size])
        w.apply_translation([x + 0.01, 0, 0])
        parts.append(w)
    return trimesh.util.concatenate(parts), [slice(12 * i, 12 * (i + 1)) for i in range(len(xs))]


def _unit(name: str, effects: Effects = NO_EFFECTS, seed: int = 0, fraction: float = 1.0) -> Unit:
    return Unit.draw(PROFILES[name].with_azimuth_fraction(fraction), np.random.default_rng(seed), effects)


def test_profiles_are_the_real_sensors():
    p = PROFILES
    assert set(p) == {"hdl64", "hdl32", "av2", "waymo", "os128"}
    el = lambda name: np.concatenate([h.sensor.elevations_deg for h in p[name].heads])  # noqa: E731
    assert p["hdl64"].n_beams == 64 and el("hdl64").max() == pytest.approx(2.0) and el("hdl64").min() == pytest.approx(-24.8)
    assert p["hdl64"].height == pytest.approx(1.73)
    assert p["hdl32"].n_beams == 32 and el("hdl32").max() == pytest.approx(10.67) and el("hdl32").min() == pytest.approx(-30.67)
    assert p["hdl32"].height == pytest.approx(1.84) and p["hdl32"].heads[0].sensor.n_azimuth == 1084
    assert p["av2"].n_beams == 64 and len(p["av2"].heads) == 2
    assert p["waymo"].n_beams == 64 and el("waymo").min() == pytest.approx(-17.6) and el("waymo").max() == pytest.approx(2.4)
    assert p["os128"].n_beams == 128 and np.ptp(el("os128")) == pytest.approx(45.0)
    # the lower AV2 head hangs upside down ~11.5 cm under the upper one, so it looks up to +25 deg
    assert AV2_DOWN_IN_RIG[2, 2] < -0.99 and AV2_DOWN_IN_RIG[2, 3] == pytest.approx(-0.115, abs=0.002)


def test_av2_beam_table_and_height_match_the_real_sweeps():
    """Per laser, the median elevation of the real points in its own head's frame is the profile's table
    (float16 coordinates: ~0.15 deg spread per point, medians within 0.05 deg); and the upper head's
    -25 deg beam meets the road where a sensor AV2_UP_HEIGHT above it would see it."""
    from hgca_core.synth.lidar import _AV2_DOWN, _AV2_UP

    for sw in av2_sweeps():
        for k in range(64):
            head = _AV2_UP if k < 32 else _AV2_DOWN
            pts = sw.points[sw.ring == k]
            pts = pts[np.linalg.norm(pts - head[:3, 3], axis=1) > 3.0]
            measured = np.median(elevations(pts, head[:3, 3], head[:3, :3]))
            assert measured == pytest.approx(VLP32C.elevations_deg[k % 32], abs=0.05), (sw.name, k)
        road = np.median(sw.points[sw.ring == 31, 2])
        assert _AV2_UP[2, 3] - road == pytest.approx(AV2_UP_HEIGHT, abs=0.03)


def test_nuscenes_rings_are_the_hdl32e_table():
    nus = nuscenes_sweep()
    measured = np.array([np.median(elevations(nus.points[nus.ring == k], nus.origin)) for k in range(32)])
    assert np.allclose(np.sort(measured), np.sort(HDL32E.elevations_deg), atol=0.35)
    assert np.all(np.diff(measured) > 0)                      # nuScenes numbers rings from the lowest beam up


def test_without_effects_a_scan_is_exact():
    unit = _unit("hdl32")
    sc = scan(make_intersector(_ground()), np.zeros(2, dtype=np.uint8), _vehicle(3.0, -2.0, 0.4), unit,
              np.random.default_rng(0), NO_EFFECTS)
    assert np.allclose(sc.points[:, 2], 0.0, atol=1e-9)
    rel = sc.points - sc.pose[:3, 3]
    el = np.degrees(np.arctan2(rel[:, 2], np.linalg.norm(rel[:, :2], axis=1)))
    beam_el = HDL32E.elevations_deg[sc.ring]
    assert np.allclose(el, beam_el, atol=1e-6) and sc.pose[2, 3] == pytest.approx(1.84)
    # every beam that meets the ground within its 100 m range does, 1084 times per revolution; the others never
    counts = np.bincount(sc.ring, minlength=32)
    assert np.all(counts[HDL32E.elevations_deg < -1.1] == 1084) and np.all(counts[HDL32E.elevations_deg > -1.0] == 0)


def test_glass_passes_windows_swallow_dark_fades():
    mesh, faces = _walls(10.0, 12.0)
    unit = _unit("os128")
    eff = replace(NO_EFFECTS, materials=True)
    hits = {}
    for name, mat in (("glass", GLASS), ("window", WINDOW), ("diffuse", DIFFUSE)):
        m = np.full(len(mesh.faces), DIFFUSE, dtype=np.uint8)
        m[faces[0]] = mat
        sc = scan(make_intersector(mesh), m, _vehicle(), unit, np.random.default_rng(1), eff)
        x = sc.points[:, 0]
        hits[name] = (np.mean((x > 10.0 - 1e-6) & (x < 10.02 + 1e-6)), np.mean(np.isclose(x, 12.0, atol=1e-6)), len(x))
    assert hits["diffuse"][0] == 1.0
    # a pane (front and back face) passes 0.9 * 0.9 of the beams on to the wall behind
    assert 0.14 < hits["glass"][0] < 0.24 and 0.76 < hits["glass"][1] < 0.86
    assert hits["window"][2] < 0.3 * hits["diffuse"][2] and hits["window"][1] == 0.0  # swallowed, none behind
    # without the materials effect glass is a wall like any other
    m = np.full(len(mesh.faces), GLASS, dtype=np.uint8)
    sc = scan(make_intersector(mesh), m, _vehicle(), unit, np.random.default_rng(1), NO_EFFECTS)
    assert np.allclose(sc.points[:, 0], 10.0)


def test_porous_crowns_let_some_beams_through():
    crown = trimesh.creation.icosphere(2, radius=2.0)
    crown.apply_translation([8.0, 0.0, 2.0])
    wall, _ = _walls(15.0)
    mesh = trimesh.util.concatenate([crown, wall])
    mats = np.r_[np.full(len(crown.faces), FOLIAGE), np.full(len(wall.faces), DIFFUSE)].astype(np.uint8)
    sc = scan(make_intersector(mesh), mats, _vehicle(), _unit("os128"), np.random.default_rng(2),
              replace(NO_EFFECTS, materials=True))
    rel = sc.points - sc.pose[:3, 3]
    ahead = np.degrees(np.arccos(rel[:, 0] / np.linalg.norm(rel, axis=1))) < 3.0   # beams through the crown's core
    on_wall = np.isclose(sc.points[ahead, 0], 15.0, atol=1e-6)
    assert 0.08 < on_wall.mean() < 0.3                   # 0.4 * 0.4 pass both leaf layers; a solid crown passes none


def test_detection_fades_with_range_and_darkness():
    p = detection_probability(np.array([10.0, 55.0, 120.0]), np.full(3, 0.1), np.ones(3), 55.0)
    assert p[0] > 0.95 and p[1] == pytest.approx(0.5) and p[2] < 0.1
    assert detection_probability(np.array([40.0]), np.array([0.035]), np.ones(1), 55.0)[0] < \
        detection_probability(np.array([40.0]), np.array([0.3]), np.ones(1), 55.0)[0] - 0.5
    eff = replace(NO_EFFECTS, detection=True)
    near_mesh, _ = _walls(8.0)
    clean = scan(make_intersector(near_mesh), np.full(12, DARK, np.uint8), _vehicle(), _unit("os128"),
                 np.random.default_rng(3), NO_EFFECTS)
    near = scan(make_intersector(near_mesh), np.full(12, DARK, np.uint8), _vehicle(), _unit("os128"),
                np.random.default_rng(3), eff)
    head_on = lambda p: np.sum(np.all(np.abs(p[:, 1:] - [0.0, 1.9]) < 3.0, axis=1))  # noqa: E731
    assert head_on(near.points) > 0.97 * head_on(clean.points)             # even dark paint returns up close
    far_mesh, _ = _walls(70.0, size=200.0)
    dark = scan(make_intersector(far_mesh), np.full(12, DARK, np.uint8), _vehicle(), _unit("os128"),
                np.random.default_rng(4), eff)
    light = scan(make_intersector(far_mesh), np.full(12, DIFFUSE, np.uint8), _vehicle(), _unit("os128"),
                 np.random.default_rng(4), eff)
    assert len(dark.points) < 0.2 * len(light.points)


def test_range_noise_grows_with_distance_and_rings_share_a_bias():
    mesh, _ = _walls(5.0)
    far, _ = _walls(40.0, size=100.0)
    unit = _unit("hdl64", replace(NO_EFFECTS, ring_noise=(0.02, 0.0, 0.0)), seed=5)
    eff = replace(NO_EFFECTS, range_noise=True)
    err = []
    for m in (mesh, far):
        sc = scan(make_intersector(m), np.zeros(12, np.uint8), _vehicle(), _unit("hdl64"), np.random.default_rng(6), eff)
        err.append(np.std(sc.points[:, 0] - (5.0 if m is mesh else 40.0)))
    assert err[1] > 1.3 * err[0] > 0.008
    # a per-beam range bias: the wall comes out as rings at different depths, same within a ring
    sc = scan(make_intersector(mesh), np.zeros(12, np.uint8), _vehicle(), unit, np.random.default_rng(7), NO_EFFECTS)
    front = np.abs(np.arctan2(sc.points[:, 1], sc.points[:, 0])) < 0.2
    rel = sc.points[front] - sc.pose[:3, 3]
    r = np.linalg.norm(rel, axis=1)
    exact = 5.0 / (rel[:, 0] / r)
    resid = r - exact
    by_ring = [resid[sc.ring[front] == k] for k in np.unique(sc.ring[front])]
    assert max(np.std(b) for b in by_ring) < 1e-6 and np.std([b.mean() for b in by_ring]) > 0.01
    assert np.allclose([b.mean() for b in by_ring], unit.range_bias[np.unique(sc.ring[front])], atol=1e-6)


def test_random_dropout_removes_its_share_of_returns_drawn_per_scan():
    mesh, _ = _walls(8.0)
    inter, unit = make_intersector(mesh), _unit("hdl64", fraction=0.5)
    n0 = len(scan(inter, np.zeros(12, np.uint8), _vehicle(), unit, np.random.default_rng(0), NO_EFFECTS).points)
    fixed = scan(inter, np.zeros(12, np.uint8), _vehicle(), unit, np.random.default_rng(0),
                 replace(NO_EFFECTS, dropout=(0.2, 0.2)))
    kept = len(fixed.points) / n0
    assert n0 > 5000 and abs(kept - 0.8) < 4 * np.sqrt(0.16 / n0)          # binomial: within 4 sd of 80 %
    # the kept returns are a subset of the exact scan's, not moved ones
    exact = scan(inter, np.zeros(12, np.uint8), _vehicle(), unit, np.random.default_rng(0), NO_EFFECTS).points
    assert np.isin(fixed.points[:, 1].round(9), exact[:, 1].round(9)).all()
    # each scan draws its own probability from the range: the kept share varies between scans, inside the range
    shares = [len(scan(inter, np.zeros(12, np.uint8), _vehicle(), unit, np.random.default_rng(s),
                       replace(NO_EFFECTS, dropout=(0.05, 0.3))).points) / n0 for s in range(12)]
    assert min(shares) > 0.7 - 0.02 and max(shares) < 0.95 + 0.02 and np.ptp(shares) > 0.05


def test_mount_jitter_moves_height_and_pitch_per_sample_and_the_ground_rings_follow():
    prof = PROFILES["hdl32"]
    units = [Unit.draw(prof, np.random.default_rng(s), replace(NO_EFFECTS, mount_jitter=(0.05, 0.7)))
             for s in range(300)]
    heights = np.array([u.mount[2, 3] for u in units])
    pitch = np.degrees([np.arcsin(-u.mount[2, 0]) for u in units])    # the beam frame's x axis tilted up / down
    assert abs(np.mean(heights) - prof.height) < 0.01 and 0.04 < np.std(heights) < 0.06
    assert np.abs(heights - prof.height).max() <= 3 * 0.05 + 1e-9      # clipped at 3 sd
    assert 0.55 < np.std(pitch) < 0.85
    still = Unit.draw(prof, np.random.default_rng(0), NO_EFFECTS)
    assert still.mount[2, 3] == pytest.approx(prof.height) and np.allclose(still.mount[:3, :3], np.eye(3))
    # a scan of flat ground from the lowest and highest drawn mount: the nearest ground ring lies where the
    # mount's height puts it (r = h / tan(-elevation), so a higher sensor sees the first ring further out)
    low, high = (units[i] for i in (np.argmin(heights), np.argmax(heights)))
    radii = []
    for u in (low, high):
        flat = Unit(u.profile, u.elevation_error_deg, u.range_bias, u.wobble, _height_only(u.mount))
        sc = scan(make_intersector(_ground()), np.zeros(2, np.uint8), _vehicle(), flat, np.random.default_rng(0),
                  NO_EFFECTS)
        assert sc.pose[2, 3] == pytest.approx(u.mount[2, 3])
        lowest = np.argmin(HDL32E.elevations_deg)
        radii.append(np.median(np.hypot(*sc.points[sc.ring == lowest, :2].T)))
    expect = [u.mount[2, 3] / np.tan(np.radians(-HDL32E.elevations_deg.min())) for u in (low, high)]
    assert radii == pytest.approx(expect, rel=0.01) and radii[1] > radii[0]


def _height_only(mount: np.ndarray) -> np.ndarray:
    """The mount without its pitch and roll: the ring radius then depends on the height alone."""
    m = np.eye(4)
    m[2, 3] = mount[2, 3]
    return m


def test_ego_body_hides_the_lowest_beams_near_the_car():
    unit = _unit("hdl32")
    full = scan(make_intersector(_ground()), np.zeros(2, np.uint8), _vehicle(), unit, np.random.default_rng(0),
                NO_EFFECTS)
    body = scan(make_intersector(_ground()), np.zeros(2, np.uint8), _vehicle(), unit, np.random.default_rng(0),
                replace(NO_EFFECTS, ego_body=True))
    low = np.argmin(HDL32E.elevations_deg)
    kept = np.sum(body.ring == low) / np.sum(full.ring == low)
    assert 0.05 < kept < 0.5                                              # real nuScenes sweep: 18 %
    high = np.argmin(np.abs(HDL32E.elevations_deg + 12.0))
    assert np.sum(body.ring == high) == np.sum(full.ring == high)


def test_pose_noise_and_drift_register_scans_with_the_believed_pose():
    mesh = _ground()
    unit = _unit("waymo", seed=1)
    rng_eff = replace(NO_EFFECTS, pose_noise=(0.01, 0.02), drift=(0.001, 0.002))
    errs = {}
    for travelled in (0.0, 15.0):
        t, a = [], []
        for seed in range(40):
            sc = scan(make_intersector(mesh), np.zeros(2, np.uint8), _vehicle(), unit, np.random.default_rng(seed),
                      rng_eff, travelled=travelled)
            true = _vehicle() @ unit.mount
            t.append(np.linalg.norm(sc.pose[:3, 3] - true[:3, 3]))
            a.append(np.degrees(np.arccos(np.clip((np.trace(sc.pose[:3, :3].T @ true[:3, :3]) - 1) / 2, -1, 1))))
        errs[travelled] = (np.median(t), np.median(a))
    assert 0.008 < errs[0.0][0] < 0.03 and 0.01 < errs[0.0][1] < 0.06           # 1 cm, 0.02 deg per axis
    assert errs[15.0][0] > errs[0.0][0] and errs[15.0][1] > errs[0.0][1]         # drift grows with travel
    # the points moved with the believed pose: the flat ground now tilts by the pose's error
    sc = scan(make_intersector(mesh), np.zeros(2, np.uint8), _vehicle(), unit, np.random.default_rng(0), rng_eff,
              travelled=15.0)
    assert np.abs(sc.points[:, 2]).max() > 1e-3


def test_motion_distortion_smears_a_moving_scan():
    mesh, _ = _walls(10.0, size=80.0)
    unit = _unit("hdl64", fraction=0.5)
    start, end = _vehicle(), _vehicle(1.0)                                 # 10 m/s over one 10 Hz turn
    found = set()
    for seed in range(12):
        sc = scan(make_intersector(mesh), np.zeros(12, np.uint8), start, unit, np.random.default_rng(seed),
                  replace(NO_EFFECTS, motion=True), vehicle_pose_end=end)
        spread = np.ptp(sc.points[:, 0])
        found.add("sharp" if spread < 1e-6 else "smeared")
        assert spread < 1.0 + 1e-6
    assert found == {"sharp", "smeared"}                  # fully compensated sometimes, partly the other times


def test_same_rng_same_scan_and_every_effect_together():
    from hgca_core.synth.dataset import Drive
    from hgca_core.synth.scene import make_scene

    scene = make_scene(5, "city")
    inter = make_intersector(scene.mesh)
    drive = Drive(scene.drive, scene.drive_up)
    unit = _unit("av2", Effects(), fraction=0.25)
    a = scan(inter, scene.face_materials, drive.pose(40.0), unit, np.random.default_rng(9), Effects(), drive.pose(40.8))
    b = scan(inter, scene.face_materials, drive.pose(40.0), unit, np.random.default_rng(9), Effects(), drive.pose(40.8))
    assert np.array_equal(a.points, b.points) and np.array_equal(a.ring, b.ring)
    assert len(a.points) > 5000 and set(np.unique(a.ring)) > set(range(32, 64)) - {63}

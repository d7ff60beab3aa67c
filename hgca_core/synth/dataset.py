"""Simulated synthetic samples in the CONTRACTS.md format (the file format: `dataset.samples`; splits of them:
`synth.splits`).

A sample is one region of one scene: the ego (center) pose on the drive fixes the region (its x axis
along the heading, its floor 1 m below the ground under the ego sensor); the input is that scan plus n-1
scans from poses within +-15 m along the drive, by a sensor profile of a real dataset with its effects
(`synth.lidar`); each sample draws its profile and its number of scans (1 to 10) from its seed. The
ground truth is the scene's visible surface inside the region.
"""
from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from hgca_core.dataset import samples
from hgca_core.geometry.raycast import EVAL128, Sensor, make_intersector, range_image
from hgca_core.geometry.region import BELOW_GROUND, DEFAULT_SIZE, GROUND_STEP, Region
from hgca_core.synth.groundtruth import RegionSurface, visible_cells
from hgca_core.synth.lidar import PROFILES, Effects, Unit, scan
from hgca_core.synth.assets import LABEL_NAMES
from hgca_core.synth.scene import GENERATOR_VERSION, STYLE_DRAWS, StreetScene, make_scene

SCANS = (1, 10)         # a sample draws its number of input scans from this range (inclusive)
EVAL_HEIGHT = 2.0       # the evaluation LiDAR rides this high above the road


@dataclass(frozen=True)
class Quality:
    """How dense a sample is. The defaults are the dataset's; tests may pass a lighter one (same code path)."""

    azimuth_fraction: float = 1.0         # of the input profiles' azimuth steps
    effects: Effects = Effects()          # real-sensor effects of the input scans
    eval_sensor: Sensor = EVAL128
    visibility_azimuth: int = 1325        # azimuth steps of the EVAL128 casts from input poses (visibility only)
    surface_density: float = 2000.0       # samples per m^2 for occupancy (all but ~1% sliver 10 cm cells hit)
    gt_surface_points: int = 200_000
    udf_points: int = 300_000
    scan_radius: float = 15.0             # other input poses lie within this arc length of the ego pose
    quantum: float = 1.0 / 1024           # stored float coordinates are rounded to this (smaller files)


DEFAULT_QUALITY = Quality()
# smoke tests and `hgca synth --quick`: the same pipeline at a fraction of the rays and samples
QUICK_QUALITY = Quality(azimuth_fraction=0.25, eval_sensor=EVAL128.with_azimuth(660), visibility_azimuth=400,
                        surface_density=300.0, gt_surface_points=30_000, udf_points=30_000)


def draw_recipe(seed: int) -> tuple[str, int]:
    """(sensor profile, number of input scans) of the sample named by `seed`: uniform over the profiles
    and over SCANS, from a stream of their own (so they do not move when the generator's other draws do)."""
    rng = np.random.default_rng([int(seed), 31337])
    names = sorted(PROFILES)
    return names[int(rng.integers(0, len(names)))], int(rng.integers(SCANS[0], SCANS[1] + 1))


class Drive:
    """The ego vehicle's path as a function of arc length: positions on the road and vehicle poses that
    pitch and roll with it."""

    def __init__(self, points: np.ndarray, up: np.ndarray | None = None) -> None:
        self.points = np.asarray(points, dtype=np.float64)
        self.up = np.tile([0.0, 0.0, 1.0], (len(self.points), 1)) if up is None else np.asarray(up, dtype=np.float64)
        seg = np.linalg.norm(np.diff(self.points[:, :2], axis=0), axis=1)
        self.s = np.concatenate([[0.0], np.cumsum(seg)])
        self.length = float(self.s[-1])

    def position(self, s: float) -> np.ndarray:
        return np.array([np.interp(s, self.s, self.points[:, i]) for i in range(3)])

    def pose(self, s: float, height: float = 0.0) -> np.ndarray:
        """4x4 vehicle->world at arc length s: x forward along the drive, z the ground's up vector, origin on
        the road (or `height` above it along z)."""
        p = self.position(s)
        fwd = self.position(min(s + 0.25, self.length)) - self.position(max(s - 0.25, 0.0))
        z = np.array([np.interp(s, self.s, self.up[:, i]) for i in range(3)])
        z /= np.linalg.norm(z)
        x = fwd - (fwd @ z) * z
        x /= np.linalg.norm(x)
        m = np.eye(4)
        m[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
        m[:3, 3] = p + height * z
        return m


@dataclass
class Simulation:
    """A sample and what it was made from: the scene, its region, and the full (uncropped, noisy) input
    scans in world coordinates with their sensor->world poses (ego first)."""

    sample: dict
    scene: StreetScene
    region: Region
    scans_world: list[np.ndarray]
    poses_world: list[np.ndarray]


def make_sample(seed: int, n_scans: int | None = None, style: str | None = None,
                size: tuple[float, float, float] = DEFAULT_SIZE, quality: Quality = DEFAULT_QUALITY,
                scene: StreetScene | None = None, profile: str | None = None,
                generator: int = GENERATOR_VERSION) -> dict:
    """The sample named by `seed`: arrays in the region frame, exactly the CONTRACTS.md keys and dtypes.
    `n_scans` and `profile` default to the seed's own draw (`draw_recipe`); `generator`: the scene generator
    version (`scene.STYLE_DRAWS`)."""
    return simulate(seed, n_scans, style, size, quality, scene, profile, generator).sample


def simulate(seed: int, n_scans: int | None = None, style: str | None = None,
             size: tuple[float, float, float] = DEFAULT_SIZE, quality: Quality = DEFAULT_QUALITY,
             scene: StreetScene | None = None, profile: str | None = None,
             generator: int = GENERATOR_VERSION) -> Simulation:
    """`make_sample`, keeping the scene and the raw scans (for `hgca synth --seed`, which writes them)."""
    drawn_profile, drawn_scans = draw_recipe(seed)
    n_scans = drawn_scans if n_scans is None else int(n_scans)
    profile = drawn_profile if profile is None else profile
    if n_scans < 1:
        raise ValueError("n_scans must be at least 1")
    if profile not in PROFILES:
        raise ValueError(f"unknown sensor profile {profile!r}; use one of {', '.join(sorted(PROFILES))}")
    scene = make_scene(seed, style, generator) if scene is None else scene
    rng = np.random.default_rng([int(seed), 104729])
    drive = Drive(scene.drive, scene.drive_up)
    half = size[0] / 2
    s0 = rng.uniform(half + 3.0, drive.length - half - 3.0)
    unit = Unit.draw(PROFILES[profile].with_azimuth_fraction(quality.azimuth_fraction), rng, quality.effects)
    ego_vehicle = drive.pose(s0)
    ego_sensor = (ego_vehicle @ unit.mount)[:3, 3]
    yaw = float(np.arctan2(ego_vehicle[1, 0], ego_vehicle[0, 0]))
    region = Region.around(ego_sensor[None], sensor=ego_sensor, ground_z=float(scene.terrain.height(ego_sensor[:2])[0]),
                           size=size, yaw=yaw)
    to_region = region.local_matrix()
    inter = make_intersector(scene.mesh)

    # input: the ego scan first, then the others (rolling shutter over one revolution at the drive speed)
    arcs = _input_arcs(rng, s0, n_scans, quality.scan_radius, drive.length)
    speed = rng.uniform(3.0, 10.0)
    turn = speed / unit.profile.rate_hz
    pts, idx, far, far_idx, poses, raw, raw_poses = [], [], [], [], [], [], []
    for i, s in enumerate(arcs):
        sc = scan(inter, scene.face_materials, drive.pose(s), unit, rng, quality.effects,
                  vehicle_pose_end=drive.pose(min(s + turn, drive.length)), travelled=abs(s - s0))
        raw.append(sc.points)
        raw_poses.append(sc.pose)
        local = region.to_local(sc.points)
        inside = region.contains_local(local)
        pts.append(local[inside])
        idx.append(np.full(int(inside.sum()), i, dtype=np.uint8))
        far.append(local[~inside])   # their rays cross the region: the free space walks them (`rays.input_rays`)
        far_idx.append(np.full(int((~inside).sum()), i, dtype=np.uint8))
        poses.append(to_region @ sc.pose)
    input_poses = np.stack(poses)

    # ground truth surface, occupancy, distance pairs
    surf = RegionSurface(scene.mesh, scene.face_labels, scene.solids, region, rng, quality.surface_density,
                         terrain=scene.terrain, ground_faces=scene.ground_faces)
    occ10, occ20 = surf.occupancy()
    in_reg = np.flatnonzero(surf.in_region)
    pick = rng.choice(in_reg, size=min(quality.gt_surface_points, len(in_reg)), replace=False)
    pick.sort()
    gt_surface, gt_label = surf.points[pick], surf.labels[surf.face[pick]]
    udf_pts = _udf_queries(rng, surf.points[in_reg], quality.udf_points, region)
    udf_dist = surf.distance(udf_pts)

    # evaluation poses where the drive enters and leaves the region, their 128-beam scans, visibility
    eval_world = [drive.pose(s, EVAL_HEIGHT) for s in _eval_arcs(rng, drive, s0, region)]
    eval_poses = np.stack([to_region @ p for p in eval_world])
    eval_scans, vis_scans = [], []
    for pw, pr in zip(eval_world, eval_poses):
        depth, o, d = range_image(inter, pw, quality.eval_sensor)
        hit = np.isfinite(depth)
        local = region.to_local(o[hit] + depth[hit][:, None] * d[hit])
        eval_scans.append(local[region.contains_local(local)])
        vis_scans.append((pr, depth))
    vis_sensor = quality.eval_sensor.with_azimuth(quality.visibility_azimuth)
    for s in arcs:
        pw = drive.pose(s) @ unit.mount
        vis_scans.append((to_region @ pw, range_image(inter, pw, vis_sensor)[0]))
    eval_scans = [_quantize(e, quality.quantum, region.size) for e in eval_scans]
    visible20 = visible_cells(region, vis_scans, quality.eval_sensor, extra_points=eval_scans)

    street = _street_box_local(scene, region)
    pitch = float(np.degrees(np.arcsin(np.clip(-unit.mount[2, 0], -1, 1))))
    meta = {"seed": int(seed), "style": scene.style, "n_scans": int(n_scans), "format_version": samples.FORMAT_VERSION,
            "generator_version": int(generator), "profile": unit.profile.name, "dataset": unit.profile.dataset,
            "sensor_height": round(float(unit.mount[2, 3]), 3), "sensor_pitch_deg": round(pitch, 3),
            "ego_arc": round(float(s0), 3), "input_arcs": [round(float(a), 3) for a in arcs],
            "speed_mps": round(float(speed), 3), "scene_faces": int(len(scene.mesh.faces)),
            "labels": list(LABEL_NAMES), "layout": scene.layout}
    size_arr = region.size
    f32 = lambda a: _quantize(a, quality.quantum, size_arr)  # noqa: E731
    # point sets sorted by x (with their per-point arrays): the files compress a third better
    inp, inp_idx = _by_x(np.concatenate(pts), np.concatenate(idx))
    far_pts, far_idx_all = _by_x(np.concatenate(far), np.concatenate(far_idx))
    gt_surface, gt_label = _by_x(gt_surface, gt_label)
    udf_pts, udf_dist = _by_x(udf_pts, udf_dist)
    sample = {
        "region": np.asarray(region.as_tuple(), dtype=np.float64),
        "input_points": f32(inp),
        "input_scan_index": inp_idx,
        "input_far_points": far_pts.astype(np.float32),   # not rounded: rounding could move a hit into the region
        "input_far_scan_index": far_idx_all,
        "input_origins": input_poses[:, :3, 3].astype(np.float32),
        "input_poses": input_poses.astype(np.float32),
        "gt_occ20": occ20.astype(np.int16),
        "gt_occ10": occ10.astype(np.int16),
        "gt_surface": f32(gt_surface),
        "gt_surface_label": gt_label.astype(np.uint8),
        "udf_points": f32(udf_pts),
        "udf_dist": (np.round(udf_dist / (quality.quantum / 4)) * (quality.quantum / 4)).astype(np.float32),
        "eval_poses": eval_poses.astype(np.float32),
        "eval_scan_0": f32(eval_scans[0]),
        "eval_scan_1": f32(eval_scans[1]),
        "visible20": visible20.astype(np.int16),
        "street_box": street.astype(np.float32),
        "ground_z": np.float32(BELOW_GROUND),
        "ground_height": _ground_height(scene, region),
        "meta": np.array(json.dumps(meta)),
    }
    return Simulation(sample, scene, region, raw, raw_poses)


def _quantize(points: np.ndarray, quantum: float, size: np.ndarray) -> np.ndarray:
    """Round region-frame coordinates to `quantum` (float32 files compress far better), never pushing a
    point inside the region across its far faces."""
    p = np.asarray(points, dtype=np.float64)
    q = np.round(p / quantum) * quantum
    over = q >= size
    q[over] = (np.floor(p / quantum) * quantum)[over]
    return q.astype(np.float32)


def _by_x(points: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    order = np.argsort(points[:, 0], kind="stable")
    return points[order], values[order]


def _input_arcs(rng: np.random.Generator, s0: float, n: int, radius: float, length: float,
                min_gap: float = 1.5) -> list[float]:
    """Ego arc first, then n-1 distinct arcs within +-radius (at least min_gap apart)."""
    arcs = [s0]
    for _ in range(2000):
        if len(arcs) == n:
            break
        s = s0 + rng.uniform(-radius, radius)
        if 0.0 <= s <= length and all(abs(s - a) >= min_gap for a in arcs):
            arcs.append(s)
    while len(arcs) < n:  # more scans than fit at min_gap: accept any distinct arc
        arcs.append(float(np.clip(s0 + rng.uniform(-radius, radius), 0.0, length)))
    return arcs


def _eval_arcs(rng: np.random.Generator, drive: Drive, s0: float, region: Region) -> list[float]:
    """Two arcs where the drive enters and leaves the region, 1-3 m inside its x/y bounds."""
    margin = rng.uniform(1.0, 3.0)
    s = np.arange(0.0, drive.length, 0.1)
    local = region.to_local(np.stack([drive.position(v) for v in s[::5]]))
    inside = np.all((local[:, :2] >= margin) & (local[:, :2] <= region.size[:2] - margin), axis=1)
    arc = s[::5][inside]
    back, ahead = arc[arc <= s0], arc[arc >= s0]
    return [float(back.min()) if len(back) else s0, float(ahead.max()) if len(ahead) else s0]


def _udf_queries(rng: np.random.Generator, surface: np.ndarray, n: int, region: Region) -> np.ndarray:
    """Surface samples displaced by Gaussian noise of 3 cm (half) and 10 cm (half), kept inside the region."""
    base = surface[rng.integers(0, len(surface), n)]
    sigma = np.where(np.arange(n) < n // 2, 0.03, 0.1)[:, None]
    q = base + rng.normal(size=base.shape) * sigma
    return q[region.contains_local(q)]


def _ground_height(scene: StreetScene, region: Region) -> np.ndarray:
    """(nx, ny) float32 height of the ground (terrain, region frame z) at region x, y = i, j * GROUND_STEP,
    covering the region: ground_z is the ground under the ego sensor only, and streets slope."""
    n = np.ceil(region.size[:2] / GROUND_STEP).astype(int) + 1
    g = np.stack(np.meshgrid(np.arange(n[0]) * GROUND_STEP, np.arange(n[1]) * GROUND_STEP, indexing="ij"), -1)
    world = region.to_world(np.c_[g.reshape(-1, 2), np.zeros(g.size // 2)])
    z = scene.terrain.height(world[:, :2]) - (region.center[2] - region.size[2] / 2)
    return np.round(z.reshape(n[0], n[1]) * 1024).astype(np.float32) / 1024


def _street_box_local(scene: StreetScene, region: Region) -> np.ndarray:
    """The main street corridor in the region frame, as the box around the part of it inside the region's
    x range (a bent street makes the box a little wider than the street), clipped to the region."""
    edges = region.to_local(np.c_[scene.corridor().reshape(-1, 2), np.zeros(scene.corridor().size // 2)])[:, :2]
    inside = (edges[:, 0] >= 0.0) & (edges[:, 0] <= region.size[0])
    local = edges[inside] if inside.any() else edges
    lo = np.clip(local.min(axis=0), 0.0, region.size[:2])
    hi = np.clip(local.max(axis=0), 0.0, region.size[:2])
    return np.array([lo[0], lo[1], hi[0], hi[1]])

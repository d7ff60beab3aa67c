"""The sensors of real datasets, simulated: beam tables and mounting of five LiDARs, and what real scans
suffer that a perfect ray caster does not.

Profiles: Velodyne HDL-64E (KITTI), HDL-32E (nuScenes), two stacked VLP-32C (Argoverse 2; the beam table
and mounting were measured from the real AV2 sweeps in tests/data/real/av2, see
benchmarks/sensor_profiles.py), the Waymo top LiDAR (the paper's input sensor) and an Ouster OS1-128.

Effects (each can be switched off in `Effects`): random dropout; returns that fade with range, incidence
and reflectivity (dark paint and tyres vanish first); glass that beams pass through, windows that swallow
them, porous crowns; range noise that grows with distance; ring-correlated calibration errors (per-beam
elevation and range offsets, as rings in KITTI scans show); the ego vehicle's own body; motion distortion
(the sensor moves during a revolution and the dataset compensates only partly); pose noise (paper: 1 cm,
0.02 deg) and registration drift that grows with distance from the ego scan.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from hgca_core.geometry.raycast import WAYMO64, Intersector, Sensor, column_poses
from hgca_core.synth.materials import ABSORB, REFLECTIVITY, TRANSMIT


@dataclass(frozen=True, eq=False)
class Head:
    """One spinning unit: its beams and its 4x4 pose in the rig frame (the rig frame is the first head's)."""

    sensor: Sensor
    mount: np.ndarray


@dataclass(frozen=True, eq=False)
class SensorProfile:
    """A real sensor setup. `height`: first head above the road (m); `range10`: range (m) at which a 10 %
    reflective target seen head-on returns half the time; `range_noise`: sigma = a + b * range (m);
    `ego_box`: the own vehicle below the sensor in the rig frame (x0, x1, y0, y1, z_top), beams into it
    give no point."""

    name: str
    dataset: str
    heads: tuple[Head, ...]
    height: float
    rate_hz: float
    range10: float
    range_noise: tuple[float, float]
    ego_box: tuple[float, float, float, float, float]

    @property
    def n_beams(self) -> int:
        return sum(len(h.sensor.elevations_deg) for h in self.heads)

    def with_azimuth_fraction(self, f: float) -> "SensorProfile":
        """The same profile with a fraction of the azimuth steps (smoke tests)."""
        heads = tuple(Head(h.sensor.with_azimuth(max(8, int(h.sensor.n_azimuth * f))), h.mount) for h in self.heads)
        return replace(self, heads=heads)


def _mount(t=(0.0, 0.0, 0.0), quat_wxyz=(1.0, 0.0, 0.0, 0.0)) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    m = np.eye(4)
    w, x, y, z = quat_wxyz
    m[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
    m[:3, 3] = t
    return m


# Velodyne HDL-64E S2 as on the KITTI car: upper block +2.0 .. -8.33 deg (1/3 deg), lower -8.83 .. -24.8 deg
HDL64E = Sensor(np.concatenate([np.linspace(2.0, -8.333, 32), np.linspace(-8.83, -24.8, 32)]), 2083, 120.0, 2.0)
# Velodyne HDL-32E (nuScenes, 20 Hz): 32 beams evenly over +10.67 .. -30.67 deg; 1084 firings per turn
HDL32E = Sensor(np.linspace(10.67, -30.67, 32), 1084, 100.0, 1.0)
# Velodyne VLP-32C beam table by laser number, as measured in the AV2 sweeps (median elevation per laser
# in the sensor frame; benchmarks/sensor_profiles.py re-measures it); 0.2 deg azimuth steps at 10 Hz
VLP32C = Sensor(np.array([6.998, -1.668, 1.666, -0.668, 14.992, -0.334, 3.332, 0.666, 1.332, 0.001, 0.999, 2.332,
                          0.332, -1.001, 4.666, 10.330, -6.146, -15.640, -3.001, -2.001, -4.000, -8.843, -4.667,
                          -3.334, -2.668, -5.332, -1.334, -7.253, -3.668, -11.310, -2.334, -24.974]), 1800, 200.0, 1.0)
# Ouster OS1-128 (Rev 6): 128 beams evenly over +-22.5 deg, 1024 columns at 10 Hz
OS1_128 = Sensor(np.linspace(22.5, -22.5, 128), 1024, 120.0, 0.8)

# AV2 extrinsics (egovehicle_SE3_sensor of log 7fab2350): the lower VLP-32C hangs upside down 11.5 cm
# below the upper one; the rig frame is the upper one's
_AV2_UP = _mount((1.35018, 0.0, 1.64042), (0.9999870714742982, 0.0, 0.0, -0.005084966495157445))
_AV2_DOWN = _mount((1.3467614766959441, 0.0045669612308231996, 1.5254961741451358),
                   (-0.0005378898980682196, -0.9949195814043752, 0.10067133271798985, -0.0001413555239330126))
AV2_DOWN_IN_RIG = np.linalg.inv(_AV2_UP) @ _AV2_DOWN
AV2_UP_HEIGHT = 2.00   # upper sensor above the road: its lowest beam (-24.97 deg) meets the road 4.29 m out
# The own vehicle as the lowest beams see it (rig frame, x0, x1, y0, y1, top): fitted to the returns per ring
# of the real nuScenes and AV2 sweeps (benchmarks/sensor_profiles.py); the others take a like-sized mount
_GENERIC_EGO = (-1.0, 0.5, -0.6, 0.6, -0.35)

PROFILES: dict[str, SensorProfile] = {p.name: p for p in (
    SensorProfile("hdl64", "KITTI", (Head(HDL64E, np.eye(4)),), 1.73, 10.0, 55.0, (0.012, 2e-4), _GENERIC_EGO),
    SensorProfile("hdl32", "nuScenes", (Head(HDL32E, np.eye(4)),), 1.84, 20.0, 50.0, (0.015, 2e-4),
                  (-1.0, 0.75, -0.65, 0.65, -0.4)),
    SensorProfile("av2", "Argoverse 2", (Head(VLP32C, np.eye(4)), Head(VLP32C, AV2_DOWN_IN_RIG)), AV2_UP_HEIGHT, 10.0,
                  100.0, (0.01, 2e-4), (-0.5, 0.25, -0.7, 0.7, -0.35)),
    SensorProfile("waymo", "Waymo (paper)", (Head(WAYMO64, np.eye(4)),), 2.0, 10.0, 60.0, (0.01, 1e-4), _GENERIC_EGO),
    SensorProfile("os128", "Ouster OS1-128", (Head(OS1_128, np.eye(4)),), 1.9, 10.0, 45.0, (0.015, 3e-4), _GENERIC_EGO),
)}


@dataclass(frozen=True)
class Effects:
    """Which real-sensor effects a scan gets, and how strong they are (defaults: what real data shows)."""

    dropout: tuple[float, float] = (0.003, 0.02)   # random dropout probability, drawn per scan
    detection: bool = True                         # returns fade with range, incidence and reflectivity
    materials: bool = True                         # glass passes, windows swallow, crowns are porous
    range_noise: bool = True
    ring_noise: tuple[float, float, float] = (0.01, 0.03, 0.005)  # per beam: range bias (m), elevation (deg),
    #                                                               and a once-per-turn range wobble (m)
    ego_body: bool = True
    motion: bool = True                            # rolling shutter, partly compensated
    pose_noise: tuple[float, float] = (0.01, 0.02)  # per scan: metres, degrees (paper)
    drift: tuple[float, float] = (0.001, 0.002)     # per metre of travel from the ego scan: metres, degrees
    mount_jitter: tuple[float, float] = (0.05, 0.7)  # mounting height (m, sd) and pitch (deg, sd) per sample


NO_EFFECTS = Effects(dropout=(0.0, 0.0), detection=False, materials=False, range_noise=False,
                     ring_noise=(0.0, 0.0, 0.0), ego_body=False, motion=False, pose_noise=(0.0, 0.0), drift=(0.0, 0.0),
                     mount_jitter=(0.0, 0.0))
# the paper's inputs: a perfect sensor, 1 cm of range noise (the profile's) and 1 cm / 0.02 deg pose noise
PAPER_EFFECTS = replace(NO_EFFECTS, range_noise=True, pose_noise=(0.01, 0.02))


@dataclass(frozen=True, eq=False)
class Unit:
    """One physical sensor of a profile as mounted on one vehicle: its calibration errors per beam and its
    mounting (height and pitch jitter). Drawn once per sample; every scan of the sample uses it."""

    profile: SensorProfile
    elevation_error_deg: np.ndarray   # (n_beams,) true minus nominal elevation
    range_bias: np.ndarray            # (n_beams,) metres
    wobble: np.ndarray                # (n_beams, 2) amplitude (m) and phase of a once-per-turn range error
    mount: np.ndarray                 # 4x4 rig -> vehicle (height above the road, pitch, roll)

    @classmethod
    def draw(cls, profile: SensorProfile, rng: np.random.Generator, effects: Effects = Effects()) -> "Unit":
        n = profile.n_beams
        bias_sd, el_sd, wob_sd = effects.ring_noise
        h_sd, pitch_sd = effects.mount_jitter
        height = profile.height + float(np.clip(rng.normal(0.0, h_sd), -3 * h_sd, 3 * h_sd)) if h_sd else profile.height
        pitch = np.radians(rng.normal(0.0, pitch_sd)) if pitch_sd else 0.0
        roll = np.radians(rng.normal(0.0, pitch_sd / 3)) if pitch_sd else 0.0
        from scipy.spatial.transform import Rotation

        mount = np.eye(4)
        mount[:3, :3] = Rotation.from_euler("yx", [pitch, roll]).as_matrix()
        mount[2, 3] = height
        return cls(profile, rng.normal(0.0, el_sd, n) if el_sd else np.zeros(n),
                   rng.normal(0.0, bias_sd, n) if bias_sd else np.zeros(n),
                   np.c_[np.abs(rng.normal(0.0, wob_sd, n)) if wob_sd else np.zeros(n), rng.uniform(0, 2 * np.pi, n)],
                   mount)


@dataclass
class Scan:
    """One revolution: points as the dataset reports them (world, registered with the believed pose),
    the beam (ring) of each point, and the believed sensor pose (what the dataset's poses file says)."""

    points: np.ndarray
    ring: np.ndarray
    pose: np.ndarray


def perturbation(rng: np.random.Generator, effects: Effects, travelled: float) -> np.ndarray:
    """4x4 error of a scan's registration (applied about the sensor): pose noise plus drift for `travelled`
    metres from the ego scan."""
    from scipy.spatial.transform import Rotation

    t_sd, r_sd = effects.pose_noise
    dt_sd, dr_sd = effects.drift
    t = rng.normal(0.0, 1.0, 3) * np.hypot(t_sd, dt_sd * travelled)
    rot = np.radians(rng.normal(0.0, 1.0, 3) * np.hypot(r_sd, dr_sd * travelled))
    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec(rot).as_matrix()
    m[:3, 3] = t
    return m


def scan(inter: Intersector, face_materials: np.ndarray, vehicle_pose: np.ndarray, unit: Unit,
         rng: np.random.Generator, effects: Effects = Effects(), vehicle_pose_end: np.ndarray | None = None,
         travelled: float = 0.0) -> Scan:
    """One revolution of `unit` mounted on a vehicle at `vehicle_pose` (4x4 vehicle -> world, z up from the
    road; moving to `vehicle_pose_end` over the revolution when `effects.motion`)."""
    prof = unit.profile
    rig0 = vehicle_pose @ unit.mount
    rig1 = vehicle_pose_end @ unit.mount if (effects.motion and vehicle_pose_end is not None) else None
    err = perturbation(rng, effects, travelled) if (any(effects.pose_noise) or any(effects.drift)) else np.eye(4)
    believed = rig0.copy()
    believed[:3, :3] = err[:3, :3] @ rig0[:3, :3]
    believed[:3, 3] = rig0[:3, 3] + err[:3, 3]
    compensation = float(rng.choice([1.0, rng.uniform(0.0, 1.0)])) if rig1 is not None else 1.0
    drop_p = rng.uniform(*effects.dropout) if effects.dropout[1] > 0 else 0.0
    pts, rings = [], []
    beam0 = 0
    for head in prof.heads:
        sen = head.sensor
        n_el = len(sen.elevations_deg)
        sl = slice(beam0, beam0 + n_el)
        beam0 += n_el
        true = Sensor(sen.elevations_deg + unit.elevation_error_deg[sl], sen.n_azimuth, sen.max_range, sen.min_range)
        rots, origins = column_poses(rig0 @ head.mount, None if rig1 is None else rig1 @ head.mount, sen.n_azimuth)
        d_head = true.directions()                                       # (E, A, 3) true beams, head frame
        d_world = np.einsum("aij,eaj->eai", rots, d_head)
        o = np.broadcast_to(origins[None], d_world.shape)
        dist, face, cos_in = _trace(inter, face_materials if effects.materials else None,
                                    o.reshape(-1, 3), d_world.reshape(-1, 3), rng)
        dist, face, cos_in = (a.reshape(d_world.shape[:2]) for a in (dist, face, cos_in))
        ok = np.isfinite(dist) & (dist >= sen.min_range) & (dist <= sen.max_range)
        if effects.ego_body:
            ok &= ~_hits_box(d_head, head.mount, prof.ego_box)
        if effects.detection:
            refl = REFLECTIVITY[face_materials[np.maximum(face, 0)]]
            ok &= rng.random(dist.shape) < detection_probability(np.where(ok, dist, 1.0), refl, cos_in, prof.range10)
        if drop_p > 0:
            ok &= rng.random(dist.shape) >= drop_p
        e, a = np.nonzero(ok)
        r = dist[e, a]
        if effects.range_noise:
            r = r + rng.normal(0.0, 1.0, len(r)) * (prof.range_noise[0] + prof.range_noise[1] * r)
        amp, phase = unit.wobble[sl][e].T
        r = r + unit.range_bias[sl][e] + amp * np.sin(2 * np.pi * a / sen.n_azimuth + phase)
        local = sen.directions()[e, a] * r[:, None]                      # reported with the nominal beam table
        w = np.einsum("nij,nj->ni", rots[a], local) + origins[a]         # motion-compensated: where it really is
        if compensation < 1.0:                                           # reported with the sweep's start pose
            h0 = rig0 @ head.mount
            w = compensation * w + (1.0 - compensation) * (local @ h0[:3, :3].T + h0[:3, 3])
        w = (w - rig0[:3, 3]) @ err[:3, :3].T + rig0[:3, 3] + err[:3, 3]  # registered with the believed pose
        pts.append(w)
        rings.append((sl.start + e).astype(np.int16))
    return Scan(np.concatenate(pts), np.concatenate(rings), believed)


def detection_probability(r: np.ndarray, reflectivity: np.ndarray, cos_incidence: np.ndarray, range10: float,
                          width: float = 0.45) -> np.ndarray:
    """Chance of a return: a logistic in the log of the received power rho * g(incidence) / r^2, with half the
    returns where a 10 % target seen head-on sits at `range10`. g = 0.5 + 0.5 cos: rough surfaces scatter
    much light back even at grazing angles (real roads return to 40-60 m)."""
    power = reflectivity * (0.5 + 0.5 * np.abs(cos_incidence)) / np.maximum(r, 1e-3) ** 2
    return 1.0 / (1.0 + np.exp(-(np.log(power) - np.log(0.1 / range10**2)) / width))


def _trace(inter: Intersector, face_materials: np.ndarray | None, origins: np.ndarray, dirs: np.ndarray,
           rng: np.random.Generator, bounces: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First returns along rays, letting beams pass through transmissive faces (with their probability) and
    be lost in absorbing ones. Returns (range or inf, face index or -1, cosine of incidence)."""
    n = len(origins)
    total, face, cos_in = np.full(n, np.inf), np.full(n, -1, dtype=np.int64), np.ones(n)
    active = np.arange(n)
    travelled = np.zeros(n)
    o = np.ascontiguousarray(origins, dtype=np.float64)
    d = np.ascontiguousarray(dirs, dtype=np.float64)
    for k in range(bounces + 1):
        dist, tri = inter.first_hits(o[active], d[active])
        hit = tri >= 0
        act, dist, tri = active[hit], dist[hit], tri[hit]
        if face_materials is not None and k < bounces:
            mat = face_materials[tri]
            u = rng.random(len(act))
            passes = u < TRANSMIT[mat]
            lost = ~passes & (u < TRANSMIT[mat] + ABSORB[mat])
        else:
            passes = lost = np.zeros(len(act), dtype=bool)
        stop = ~passes & ~lost
        s = act[stop]
        total[s] = travelled[s] + dist[stop]
        face[s] = tri[stop]
        cos_in[s] = np.einsum("ij,ij->i", inter.normals[tri[stop]], d[s])
        go = act[passes]
        if len(go) == 0:
            break
        step = dist[passes] + 1e-3
        travelled[go] += step
        o[go] = o[go] + step[:, None] * d[go]
        active = go
    return total, face, cos_in


def _hits_box(d_head: np.ndarray, mount: np.ndarray, box) -> np.ndarray:
    """(E, A) beams of a head that run into the ego vehicle's box (rig frame, below the sensor) before 6 m."""
    x0, x1, y0, y1, z_top = box
    d = d_head @ mount[:3, :3].T
    o = mount[:3, 3]
    down = d[..., 2] < -1e-6
    t = np.where(down, (z_top - o[2]) / np.where(down, d[..., 2], -1.0), 0.0)   # where the beam meets the roof plane
    px, py = o[0] + t * d[..., 0], o[1] + t * d[..., 1]
    return down & (t > 0) & (t < 6.0) & (px > x0) & (px < x1) & (py > y0) & (py < y1)

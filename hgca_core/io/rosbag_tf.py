"""Sensor poses from a bag's /tf and /tf_static: the chain from a cloud's frame up to the root of its tf tree.

tf stores each transform as an edge parent -> child (the child's pose in the parent frame); a frame has at most
one parent, so following parents from the sensor frame ends at the tree's root (map, odom, world...), the fixed
frame the clouds are accumulated in. Dynamic edges are interpolated at each cloud's stamp (linear translation,
slerp rotation); a stamp more than `TOLERANCE_S` outside an edge's recorded span has no pose (the frame is
refused when it is read, not extrapolated), since a guessed pose would misplace that whole sweep.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from hgca_core.errors import InputError

TOLERANCE_S = 0.1


def frame_name(name: str) -> str:
    """tf frame ids without the leading '/' ROS 1 allowed ('/base_link' and 'base_link' are one frame)."""
    return str(name).lstrip("/")


@dataclass
class Edge:
    """The samples of one parent -> child transform: times (ns), translations, quaternions (x, y, z, w)."""

    parent: str
    static: bool
    times: list[int] = field(default_factory=list)
    translations: list[tuple[float, float, float]] = field(default_factory=list)
    rotations: list[tuple[float, float, float, float]] = field(default_factory=list)


class TfTree:
    """The transforms of a bag's /tf (dynamic) and /tf_static (static) messages."""

    def __init__(self, source: str) -> None:
        self.source = source  # the bag, for messages
        self.edges: dict[str, Edge] = {}
        self.conflicts: dict[str, str] = {}  # child -> a second parent it was given (an error if a chain uses it)

    def add(self, message: object, static: bool) -> None:
        """Record a tf2_msgs/TFMessage's transforms; a child given two parents is noted (not a tree)."""
        for ts in message.transforms:  # type: ignore[attr-defined]
            child, parent = frame_name(ts.child_frame_id), frame_name(ts.header.frame_id)
            edge = self.edges.get(child)
            if edge is None or (edge.static and not static):  # dynamic samples take over a static edge
                edge = self.edges[child] = Edge(parent, static)
            elif edge.parent != parent:
                self.conflicts.setdefault(child, parent)
                continue
            elif static != edge.static:
                continue
            tr, q = ts.transform.translation, ts.transform.rotation
            stamp = int(ts.header.stamp.sec) * 1_000_000_000 + int(getattr(ts.header.stamp, "nanosec", 0))
            edge.times.append(stamp)
            edge.translations.append((float(tr.x), float(tr.y), float(tr.z)))
            edge.rotations.append((float(q.x), float(q.y), float(q.z), float(q.w)))

    def chain(self, frame: str) -> list[str]:
        """The frames from `frame` up to its root (`[frame]` alone when tf does not know its parent)."""
        out = [frame_name(frame)]
        while out[-1] in self.edges:
            if out[-1] in self.conflicts:
                raise InputError(f"tf frame {out[-1]!r} has two parents, {self.edges[out[-1]].parent!r} and "
                                 f"{self.conflicts[out[-1]]!r}: the tf tree is ambiguous", self.source)
            parent = self.edges[out[-1]].parent
            if parent in out:
                raise InputError(f"tf has a loop through frame {parent!r}", self.source)
            out.append(parent)
        return out

    def _edge_poses(self, child: str, stamps: np.ndarray, problems: list[str | None]) -> np.ndarray:
        """(n, 4, 4) child->parent matrices at `stamps` (ns); a stamp the edge does not cover gets the nearest
        end's pose and its reason in `problems` (the first reason per stamp is kept)."""
        e = self.edges[child]
        t = np.asarray(e.times, dtype=np.int64)
        trans = np.asarray(e.translations, dtype=np.float64)
        quats = np.asarray(e.rotations, dtype=np.float64)
        bad = ~np.isfinite(trans).all(axis=1) | ~np.isfinite(quats).all(axis=1) | (np.linalg.norm(quats, axis=1) < 1e-9)
        if bad.any():
            raise InputError(f"tf transform {e.parent!r} -> {child!r} at {t[bad][0] / 1e9:.3f} s is not a finite "
                             "translation and unit quaternion", self.source)
        out = np.tile(np.eye(4), (len(stamps), 1, 1))
        if e.static:
            out[:, :3, :3] = Rotation.from_quat(quats[-1]).as_matrix()
            out[:, :3, 3] = trans[-1]
            return out
        order = np.argsort(t, kind="stable")
        t, trans, quats = t[order], trans[order], quats[order]
        last = np.r_[t[1:] != t[:-1], True]  # of equal stamps the last sample holds
        t, trans, quats = t[last], trans[last], quats[last]
        tol = int(TOLERANCE_S * 1e9)
        outside = (stamps < t[0] - tol) | (stamps > t[-1] + tol)
        for k in np.flatnonzero(outside):
            problems[k] = problems[k] or (f"no tf for frame {child!r} (in {e.parent!r}) at the cloud stamp "
                                          f"{stamps[k] / 1e9:.3f} s: /tf covers it from {t[0] / 1e9:.3f} to "
                                          f"{t[-1] / 1e9:.3f} s")
        at = np.clip(stamps, t[0], t[-1])
        rel = (at - t[0]).astype(np.float64) / 1e9
        knots = (t - t[0]).astype(np.float64) / 1e9
        for k in range(3):
            out[:, k, 3] = np.interp(rel, knots, trans[:, k])
        rots = Rotation.from_quat(quats)
        out[:, :3, :3] = (Slerp(knots, rots)(rel) if len(t) > 1 else rots[[0] * len(rel)]).as_matrix()
        return out

    def poses(self, frame: str, stamps: np.ndarray) -> tuple[np.ndarray, list[str | None]]:
        """(n, 4, 4) sensor->root poses of `frame` at `stamps` (ns), the chain's edges composed, and for each
        stamp None or why tf does not give its pose."""
        stamps = np.asarray(stamps, dtype=np.int64)
        chain = self.chain(frame)
        out = np.tile(np.eye(4), (len(stamps), 1, 1))
        problems: list[str | None] = [None] * len(stamps)
        for child in reversed(chain[:-1]):  # root-most edge first: root <- ... <- sensor
            out = out @ self._edge_poses(child, stamps, problems)
        return out, problems

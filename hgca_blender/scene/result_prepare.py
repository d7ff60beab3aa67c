"""The numpy half of putting results into the scene: everything a result mesh needs, computed off the main thread.

Reading a completion's .npz files, placing them relative to the scene origin, the samples' agreement, the colours,
the class labels and the mesh edges are numpy work that takes seconds for a full completion. Here it runs on a
worker thread (`result_insert` starts it), so Blender's main thread only copies finished arrays into meshes.
Nothing here touches Blender data: the caller reads the scene origin first and passes it in.

Edges: Blender's `mesh.update(calc_edges=True)` takes about as long as everything else together (0.3 s for
400k triangles, 1.1 s for 2M) in one call that cannot be split. The same edges are computed here instead (each
triangle side once, as (low, high) vertex pairs, and each corner's edge), so the main thread only stores them.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from . import colors, confidence, georef, semantics
from .mesh_build import read_result


@dataclass
class MeshArrays:
    """A triangle mesh as Blender stores it: float32 positions, corner vertices, edges and each corner's edge."""

    vertices: np.ndarray     # (V, 3) float32, relative to the object's location
    faces: np.ndarray        # (F, 3) int32
    edges: np.ndarray | None       # (E, 2) int32 (low, high); None: degenerate faces, Blender computes them
    corner_edge: np.ndarray | None  # (3F,) int32


@dataclass
class ClassPart:
    """One class of a labelled sample as a mesh of its own (the panel's *Collections* per class)."""

    name: str
    mesh: MeshArrays


@dataclass
class SampleArrays:
    """Everything one result object is built from; made on the worker thread."""

    name: str
    mesh: MeshArrays
    location: np.ndarray            # (3,) float64, whole metres (georef.place)
    observed: np.ndarray            # (V,) float32 observed_distance
    observed_rgba: np.ndarray       # (V, 4) float32
    agreement: np.ndarray | None = None        # (V,) float32, k > 1 samples
    agreement_rgba: np.ndarray | None = None   # (V, 4) float32
    labels: tuple | None = None     # (face labels (F,), label agreement (F,) or None, class names)
    class_parts: list[ClassPart] | None = None

    @property
    def size(self) -> int:
        """Elements to copy, the unit of the insertion's progress."""
        parts = sum(element_count(p.mesh) for p in self.class_parts or [])
        return element_count(self.mesh) + parts


def element_count(mesh: MeshArrays) -> int:
    edges = len(mesh.edges) if mesh.edges is not None else 3 * len(mesh.faces)
    return len(mesh.vertices) + edges + 4 * len(mesh.faces)


def triangle_edges(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(edges (E, 2) int32 as (low, high), corner_edge (3F,) int32) of triangles `faces`: corner c's edge joins
    its vertex and the next corner's (Blender's convention). None when a face repeats a vertex."""
    f = np.asarray(faces, dtype=np.int64)
    nxt = np.roll(f, -1, axis=1)
    lo, hi = np.minimum(f, nxt).ravel(), np.maximum(f, nxt).ravel()
    if np.any(lo == hi):
        return None
    keys, corner_edge = np.unique(lo * max(int(n_vertices), 1) + hi, return_inverse=True)
    edges = np.stack([keys // max(int(n_vertices), 1), keys % max(int(n_vertices), 1)], axis=1)
    return edges.astype(np.int32), corner_edge.astype(np.int32).ravel()


def mesh_arrays(vertices: np.ndarray, faces: np.ndarray) -> MeshArrays:
    v = np.ascontiguousarray(vertices, dtype=np.float32)
    f = np.ascontiguousarray(faces, dtype=np.int32)
    found = triangle_edges(f, len(v)) if len(f) else (np.zeros((0, 2), np.int32), np.zeros(0, np.int32))
    edges, corner_edge = found if found is not None else (None, None)
    return MeshArrays(v, f, edges, corner_edge)


def class_parts(mesh: MeshArrays, labels: np.ndarray, names: tuple[str, ...]) -> list[ClassPart]:
    """Each class present as a mesh of its own faces (the vertices they use, renumbered), in class order; the same
    arrays `semantics.class_collections` reads back from the built object."""
    parts = []
    for v in (int(x) for x in np.unique(labels)):
        used, f = np.unique(mesh.faces[labels == v], return_inverse=True)
        parts.append(ClassPart(names[v], mesh_arrays(mesh.vertices[used], f.reshape(-1, 3))))
    return parts


def prepare_results(paths: list[Path], origin: np.ndarray, run_name: str, class_collections: bool = False,
                    note: Callable[[str], None] = lambda text: None) -> list[SampleArrays]:
    """A completion's samples ("<run> sample i"), as `mesh_build.build_results` makes them: checked, placed
    relative to `origin`, with colours, agreement (k > 1), labels and, with `class_collections`, sample 0's classes
    as parts. Raises ValueError (a damaged file) before anything reaches Blender. `note(text)`: what it does now."""
    k = len(paths)
    arrays = []
    for i, p in enumerate(paths):
        note(f"Reading sample {i + 1} of {k}")
        arrays.append(read_result(Path(p)))
    note(f"Comparing the {k} samples")
    shares = confidence.agreement([a.vertices.astype(np.float64) + a.offset for a in arrays]) \
        if len(arrays) > 1 else [None] * len(arrays)
    samples = []
    for i, (arr, path) in enumerate(zip(arrays, paths)):
        note(f"Preparing sample {i + 1} of {k}")
        sample = _sample(f"{run_name} sample {i}", arr, origin, shares[i])
        sample.labels = semantics.read_labels(Path(path))
        if sample.labels is not None and class_collections and i == 0:
            sample.class_parts = class_parts(sample.mesh, sample.labels[0], sample.labels[2])
        samples.append(sample)
    return samples


def prepare_tile(paths: list[Path], origin: np.ndarray, run_name: str, index: int) -> list[SampleArrays]:
    """A drive tile's samples ("<run> tile i sample k"), as `drive_job.DriveResults` makes them (no agreement)."""
    return [_sample(f"{run_name} tile {index} sample {k}", read_result(Path(p)), origin, None)
            for k, p in enumerate(paths)]


def _sample(name: str, arr, origin: np.ndarray, share: np.ndarray | None) -> SampleArrays:
    vertices, location = georef.place(arr.vertices, arr.offset, np.zeros(3) if origin is None else origin)
    sample = SampleArrays(name, mesh_arrays(vertices, arr.faces), location,
                          np.ascontiguousarray(arr.observed_distance, dtype=np.float32),
                          confidence.observed_colors(arr.observed_distance))
    if share is not None:
        sample.agreement = np.ascontiguousarray(share, dtype=np.float32)
        sample.agreement_rgba = confidence.agreement_colors(share, colors.RAMP)
    return sample

"""What each face does to a LiDAR beam: how much light it sends back and whether the beam goes on through.

Real scans have holes where the sensor gets nothing back: glass (the beam passes, or reflects away),
dark paint and tyres (too little light at range), and porous tree crowns (some beams pass between the
leaves and hit what lies behind). Faces carry a material id; a face built without one takes its label's
default. The ground truth ignores materials: a shop window is surface the completion should restore.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hgca_core.synth.primitives import DEFAULT_MATERIAL


@dataclass(frozen=True)
class Material:
    name: str
    reflectivity: float   # diffuse (Lambertian) reflectivity, 0..1
    transmit: float       # probability that a beam hitting the face passes on through it
    absorb: float = 0.0   # probability that the beam is lost there (into a dark room behind a window)


MATERIALS = (
    Material("diffuse", 0.30, 0.0),    # plaster, concrete, painted wood
    Material("asphalt", 0.2, 0.0),
    Material("dark", 0.035, 0.0),      # black paint, tyres, dark cladding
    Material("glass", 0.08, 0.9),      # car windows, shelter panes: most beams pass on through
    Material("foliage", 0.45, 0.4),    # leaf layers of a crown or hedge: porous
    Material("retro", 0.95, 0.0),      # retro-reflective sign faces
    Material("paint", 0.25, 0.0),      # car paint
    Material("bark", 0.20, 0.0),
    Material("fabric", 0.15, 0.0),     # clothes
    Material("window", 0.08, 0.0, 0.8),  # building windows: the beam goes into the room and rarely comes back
)
DIFFUSE, ASPHALT, DARK, GLASS, FOLIAGE, RETRO, PAINT, BARK, FABRIC, WINDOW = range(len(MATERIALS))
REFLECTIVITY = np.array([m.reflectivity for m in MATERIALS])
TRANSMIT = np.array([m.transmit for m in MATERIALS])
ABSORB = np.array([m.absorb for m in MATERIALS])
# default material of each semantic label (assets.LABEL_NAMES order)
LABEL_DEFAULT = np.array([ASPHALT, DIFFUSE, DIFFUSE, PAINT, FOLIAGE, PAINT, DIFFUSE, GLASS, FABRIC], dtype=np.uint8)


def resolve(materials: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Per-face material ids with "label default" replaced by the label's material."""
    m = np.asarray(materials, dtype=np.uint8).copy()
    unset = m == DEFAULT_MATERIAL
    m[unset] = LABEL_DEFAULT[np.asarray(labels)[unset]]
    return m

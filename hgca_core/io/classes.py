"""The semantic classes a labelled mesh carries, one vocabulary for every writer, reader and front end.

The order is the synthetic streets' `LABEL_NAMES` (`hgca_core.synth.assets`): a face's `label` is an index into
CLASS_NAMES in every format (PLY face property, NPZ `face_label` with `label_names`, GLB primitive names).
CLASS_COLORS are display colours (sRGB, 0-255): renderings, the GLB materials and the Blender add-on's default
palette, which the user may change there.
"""
from __future__ import annotations

CLASS_NAMES = ("road", "sidewalk", "building", "car", "tree", "pole", "fence", "shelter", "person")
CLASS_COLORS = ((90, 90, 96), (190, 170, 150), (200, 90, 60), (40, 110, 230), (60, 170, 60), (240, 220, 40),
                (160, 110, 200), (40, 200, 200), (250, 60, 160))

"""The shipped semantic head: a small file of kind 'semantics', read with weights_only, that labels the bundled
example's cells with classes a street has."""
from __future__ import annotations

import numpy as np
import pytest

from hgca_core.errors import InputError
from hgca_core.models.weights import load_file, load_semantics, shipped


def test_shipped_head_is_small_and_of_its_kind():
    path = shipped("semantics")
    assert path.is_file() and path.stat().st_size < 2 * 2**20
    blob = load_file(path)
    assert blob["kind"] == "semantics" and blob["meta"].get("steps", 0) > 0
    head = load_semantics()
    assert not head.training and all(p.dtype.is_floating_point for p in head.parameters())


def test_shipped_head_labels_a_street():
    """The bundled example's input cells are mostly ground and facades: road + sidewalk + building measured 63 % of them
    with the shipped head (step 4,150; 67 % at step 206); below half means a broken head or features."""
    from hgca_core.geometry.region import Region
    from hgca_core.geometry.voxel import COARSE, voxelize
    from hgca_core.io import read_scans
    from hgca_core.models.semantics import predict
    from hgca_core.commands.demo import EXAMPLE_DIR
    import json

    poses = EXAMPLE_DIR / "poses.json"
    from hgca_core.io.poses import load_poses

    scans = [str(EXAMPLE_DIR / e.file) for e in load_poses(poses)]
    pts = read_scans(scans, poses=str(poses)).points
    region = Region.from_tuple(json.loads(poses.read_text())["region"])
    local = region.to_local(pts)
    cells = voxelize(local[region.contains_local(local)], COARSE, region.size)
    labels, _ = predict(load_semantics(), cells, np.ones(len(cells), bool))
    share = np.bincount(labels, minlength=9) / len(labels)
    assert share[[0, 1, 2]].sum() > 0.5, share


def test_coarse_weights_are_refused_as_a_semantic_head():
    with pytest.raises(InputError, match="semantic"):
        load_semantics(shipped("coarse"))

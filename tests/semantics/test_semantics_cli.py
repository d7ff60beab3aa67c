"""`hgca complete --semantics` and `hgca_core.complete(semantics=True)` end to end on a tiny region with small
untrained weights: labels in every format, the same geometry as without them, clear errors."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch
import trimesh
from plyfile import PlyData

from hgca_testdata import tiny_scan_file
from hgca_core.io.classes import CLASS_NAMES
from hgca_core.models.semantics import SemanticHead, SemanticsConfig
from hgca_core.training.export import save_weights

REGION = "103,203,1,6,6,4"


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    return tiny_scan_file(tmp_path_factory.mktemp("scan"))


@pytest.fixture(scope="module")
def head_weights(tmp_path_factory):
    torch.manual_seed(1)
    path = tmp_path_factory.mktemp("sem") / "semantics_small.pt"
    save_weights(path, SemanticHead(SemanticsConfig(channels=(8, 8, 16))), {"stage": "test"})
    return path


def _run(*args):
    return subprocess.run([sys.executable, "-m", "hgca_core.cli", "complete", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


@pytest.mark.slow   # minutes on 2 cores: `make test-slow` (CI runs it)
def test_cli_labels_every_format_and_keeps_the_geometry(small_weights, head_weights, scan, tmp_path):
    base = ["--weights", small_weights, "--region", REGION, "--stage", "coarse", "--samples", 2, "--seed", 3,
            "--progress", "none"]
    plain = _run(scan, "-o", tmp_path / "plain.ply", *base)
    assert plain.returncode == 0, plain.stderr
    for ext in ("ply", "npz", "glb"):
        res = _run(scan, "-o", tmp_path / f"lab.{ext}", *base, "--semantics-weights", head_weights)
        assert res.returncode == 0, res.stderr
    for i in range(2):
        a, b = PlyData.read(tmp_path / f"plain_s{i}.ply"), PlyData.read(tmp_path / f"lab_s{i}.ply")
        for axis in "xyz":
            np.testing.assert_array_equal(a["vertex"].data[axis], b["vertex"].data[axis])
        np.testing.assert_array_equal(np.vstack(a["face"].data["vertex_indices"]),
                                      np.vstack(b["face"].data["vertex_indices"]))
        assert "label" not in a["face"].data.dtype.names
        label = b["face"].data["label"]
        agree = b["face"].data["label_agreement"]
        assert len(label) == len(b["face"].data) > 0 and label.max() < len(CLASS_NAMES)
        assert np.all((agree >= 0.5) & (agree <= 1.0))     # two samples: each face agrees with itself at least
        with np.load(tmp_path / f"lab_s{i}.npz") as z:
            np.testing.assert_array_equal(z["face_label"], label)
            np.testing.assert_allclose(z["face_label_agreement"], agree)
            assert tuple(z["label_names"]) == CLASS_NAMES
        scene = trimesh.load(tmp_path / f"lab_s{i}.glb", process=False)
        names = {g.visual.material.name for g in scene.geometry.values()}
        assert names == {CLASS_NAMES[v] for v in np.unique(label)}
        assert sum(len(g.faces) for g in scene.geometry.values()) == len(label)


def test_python_api_labels_faces(small_weights, head_weights, scan):
    import hgca_core

    with np.load(scan) as z:
        pts = z["points"]
    region = hgca_core.Region.parse(REGION)
    a = hgca_core.complete(pts, region=region, stage="coarse", weights=small_weights, semantics=True,
                           semantics_weights=head_weights)
    b = hgca_core.complete(pts, region=region, stage="coarse", weights=small_weights)
    label = a[0].mesh.face_attributes["label"]
    assert label.shape == (len(a[0].faces),) and label.dtype == np.uint8
    np.testing.assert_array_equal(a[0].mesh.face_attributes["label_agreement"], 1.0)
    np.testing.assert_array_equal(a[0].vertices, b[0].vertices)
    assert "label" not in b[0].mesh.face_attributes


def test_wrong_semantics_weights_are_one_clear_error(small_weights, scan, tmp_path):
    res = _run(scan, "-o", tmp_path / "m.ply", "--weights", small_weights, "--region", REGION, "--stage", "coarse",
               "--semantics-weights", small_weights, "--progress", "none")
    assert res.returncode == 2
    lines = [ln for ln in res.stderr.splitlines() if "error" in ln]
    assert len(lines) == 1 and "hgca complete: error:" in lines[0] and "coarse_small.pt" in lines[0]
    assert "semantic" in lines[0]
    assert not list(tmp_path.glob("m_s*"))

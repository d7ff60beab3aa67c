"""Labels never change the geometry: the full stage (coarse chain, fine chain, meshing) with and without
`semantics=True` gives byte-identical vertices, faces and per-vertex / per-face data for every sample, and every
format written from the labelled result holds the same triangles."""
from __future__ import annotations

import hashlib

import numpy as np
import pytest
import torch
import trimesh

from hgca_testdata import tiny_scan_file
from hgca_core.models.semantics import SemanticHead, SemanticsConfig
from hgca_core.training.export import save_weights

REGION = "103,203,1,3,3,3"   # a 3 m corner of the tiny scan: tens of thousands of faces in seconds


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    """Small untrained coarse, fine and semantic weights, biased so that the full stage makes a mesh: the fine
    chain's occupancy logit at 0 (it keeps about half its cells) and the decoded distance below the meshing level.
    Unbiased, an untrained chain dies and there is no geometry to compare."""
    from hgca_core.models.autoencoder import Autoencoder, AutoencoderConfig
    from hgca_core.models.cgca import CGCAConfig, CGCAKernel
    from hgca_core.models.gca import GCAConfig, GCAKernel

    d = tmp_path_factory.mktemp("w")
    torch.manual_seed(0)
    coarse = save_weights(d / "coarse.pt", GCAKernel(GCAConfig(channels=(8, 8, 16, 16, 16), steps=3)),
                          {"stage": "test"})
    kernel, autoencoder = CGCAKernel(CGCAConfig(channels=(8, 8, 8, 8, 8), steps=2)), Autoencoder(AutoencoderConfig())
    with torch.no_grad():
        kernel.head[2].bias[0] = 0.0
        autoencoder.fc_out.bias.fill_(-1.0)
    fine = save_weights(d / "fine.pt", kernel, {"stage": "test"}, autoencoder=autoencoder)
    head = save_weights(d / "sem.pt", SemanticHead(SemanticsConfig(channels=(8, 8, 16))), {"stage": "test"})
    return coarse, fine, head


def geometry_digest(mesh: trimesh.Trimesh) -> str:
    """sha256 of a mesh's geometry: vertices, faces, normals and every vertex / face attribute but the labels."""
    h = hashlib.sha256()
    for a in (mesh.vertices, mesh.faces, mesh.vertex_normals):
        h.update(np.ascontiguousarray(a).tobytes())
    for where in (mesh.vertex_attributes, mesh.face_attributes):
        for k in sorted(where):
            if not k.startswith("label"):
                h.update(k.encode() + np.ascontiguousarray(where[k]).tobytes())
    return h.hexdigest()


def test_full_stage_geometry_is_byte_identical_with_labels(weights, tmp_path):
    import hgca_core
    from hgca_core.io import write_mesh

    coarse, fine, head = weights
    with np.load(tiny_scan_file(tmp_path)) as z:
        pts = z["points"]
    region = hgca_core.Region.parse(REGION)
    kw = dict(region=region, stage="full", samples=2, seed=3, weights=coarse, fine_weights=fine)
    plain = hgca_core.complete(pts, **kw)
    labelled = hgca_core.complete(pts, **kw, semantics=True, semantics_weights=head)
    assert len(plain) == len(labelled) == 2
    for a, b in zip(plain, labelled):
        assert len(a.faces) > 0
        assert "label" in b.mesh.face_attributes and "label" not in a.mesh.face_attributes
        assert geometry_digest(a.mesh) == geometry_digest(b.mesh)
        np.testing.assert_array_equal(a.coarse_cells, b.coarse_cells)
        # the GLB regroups faces by class: the same triangles, in another order
        tri = []
        for name, m in (("plain", a.mesh), ("lab", b.mesh)):
            scene = trimesh.load(write_mesh(tmp_path / f"{name}.glb", m), process=False)
            t = np.concatenate([g.vertices[g.faces] for g in scene.geometry.values()])
            tri.append(t.reshape(len(t), -1)[np.lexsort(t.reshape(len(t), -1).T[::-1])])
        np.testing.assert_array_equal(tri[0], tri[1])

"""Fixtures of the drive tests: small untrained coarse weights (plumbing, not quality) and a small drive."""
from __future__ import annotations

import pytest
import torch

from hgca_core.models.gca import GCAConfig, GCAKernel
from hgca_core.training.export import save_weights


@pytest.fixture(scope="session")
def drive_weights(tmp_path_factory):
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("w") / "coarse_small.pt"
    save_weights(path, GCAKernel(GCAConfig(channels=(8, 8, 16, 16, 16), steps=3)), {"stage": "test"})
    return path

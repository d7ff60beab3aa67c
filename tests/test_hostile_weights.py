"""Weights that load but are wrong (the second hostile campaign): their values are checked as well as their
shapes, and the refusal names the file and the tensor or key."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from hgca_core.errors import InputError
from hgca_core.models.weights import load_coarse, load_file, save_file, shipped


def _tampered(tmp_path: Path, change) -> Path:
    blob = load_file(shipped("coarse"))
    change(blob)
    return save_file(blob, tmp_path / "tampered.pt")


def test_a_negative_batchnorm_variance_is_refused_by_name(tmp_path: Path) -> None:
    def negative(blob: dict) -> None:
        name = next(k for k in blob["state_dict"] if k.endswith("running_var"))
        blob["state_dict"][name] = -blob["state_dict"][name].abs() - 0.1

    path = _tampered(tmp_path, negative)
    with pytest.raises(InputError, match=r"running_var.*negative variance") as info:
        load_coarse(path)
    assert str(path) in str(info.value)


def test_a_config_nested_a_hundred_lists_deep_is_refused(tmp_path: Path) -> None:
    """(torch.save pickles only a few hundred levels; the check itself walks any depth without recursing.)"""
    def nested(blob: dict) -> None:
        deep: list = []
        for _ in range(100):
            deep = [deep]
        blob["config"]["notes"] = deep

    path = _tampered(tmp_path, nested)
    with pytest.raises(InputError, match="'notes' is nested more than 4 levels deep") as info:
        load_coarse(path)
    assert str(path) in str(info.value)


def test_the_shipped_weights_pass_the_value_checks() -> None:
    model, _ = load_coarse(shipped("coarse"))
    assert isinstance(model, torch.nn.Module)

"""Packed coarse samples (`hgca synth --pack`): the coarse stage trains and validates on them exactly as on the full
samples they came from, they are much smaller, and what needs the full samples refuses them by name."""
import shutil

import numpy as np
import pytest
import torch

from hgca_core.cli import main
from hgca_core.dataset.packed import is_packed
from hgca_core.errors import InputError
from hgca_core.models.cgca import CGCAConfig
from hgca_core.models.gca import GCAConfig
from hgca_core.training import data
from hgca_core.training.coarse import CoarseTask
from hgca_core.training.fine import FineTask
from hgca_core.training.pack import pack_dataset

pytestmark = pytest.mark.usefixtures("one_thread")
SMALL = dict(channels=(8, 8, 16, 16, 16), steps=3, free_space=True)


@pytest.fixture
def full(tiny_dataset, tmp_path):
    root = tmp_path / "full"
    shutil.copytree(tiny_dataset, root)
    return root


@pytest.fixture
def packed(full, tmp_path):
    out = tmp_path / "packed"
    assert main(["synth", "--pack", str(full), "--out", str(out)]) == 0
    return out


def test_packed_samples_hold_the_coarse_cells_of_their_source(full, packed):
    pairs = [(f, packed / f.parent.name / f.name) for f in sorted(full.glob("*/sample_*.npz"))]
    assert len(pairs) == 5 and all(p.exists() and is_packed(p) and not is_packed(f) for f, p in pairs)
    for f, p in pairs:
        (s0, gt, grid), (ps0, pgt, pgrid) = data.coarse_pair(f), data.coarse_pair(p)
        assert grid == pgrid
        for a, b in ((s0, ps0), (gt, pgt), (data.free_cells(f), data.free_cells(p))):
            assert len(a) > 0 and np.array_equal(data.unique_rows(np.asarray(a, np.int64)), b)
        if f.parent.name == "val":
            assert np.array_equal(data.unique_rows(data.visible_cells(f)), data.visible_cells(p))
        else:   # the train split does not carry the visible cells (validation alone scores them)
            assert "visible20" not in np.load(p).files
        assert p.stat().st_size < f.stat().st_size / 3


def test_coarse_examples_and_validation_are_the_same_on_packed_data(full, packed):
    a, b = CoarseTask(str(full), GCAConfig(**SMALL), crop=16), CoarseTask(str(packed), GCAConfig(**SMALL), crop=16)
    assert [f.name for f in a.train_files] == [f.name for f in b.train_files]
    for seed in range(4):
        ca, cb = a.new_example(np.random.default_rng(seed)), b.new_example(np.random.default_rng(seed))
        assert ca.grid == cb.grid
        assert torch.equal(ca.s0, cb.s0) and torch.equal(ca.gt, cb.gt)
        assert torch.equal(ca.extra["free"], cb.extra["free"])
    torch.manual_seed(0)
    module = a.build()
    assert a.validate(module) == b.validate(module)


def test_packing_resumes_and_refuses_what_it_cannot_do(full, packed, tmp_path, capsys):
    first = {p: p.stat().st_mtime_ns for p in packed.glob("*/sample_*.npz")}
    assert main(["synth", "--pack", str(full), "--out", str(packed)]) == 0          # up to date: nothing rewritten
    assert {p: p.stat().st_mtime_ns for p in packed.glob("*/sample_*.npz")} == first
    assert (packed / "packed.json").exists()
    for argv, says in ((["--pack", str(packed), "--out", str(tmp_path / "again")], "already a packed sample"),
                       (["--pack", str(full), "--out", str(full)], "output folder is an input"),
                       (["--pack", str(tmp_path / "nothing"), "--out", str(tmp_path / "o")], "no samples"),
                       (["--pack", str(full), "--count", "3", "--out", str(tmp_path / "o")], "--count")):
        capsys.readouterr()
        assert main(["synth", *argv]) == 2
        assert says in capsys.readouterr().err


def test_what_needs_full_samples_refuses_packed_ones(packed):
    with pytest.raises(InputError, match="packed coarse sample"):
        FineTask(str(packed), CGCAConfig(channels=(8, 8, 8, 8, 8), free_space=True), autoencoder="unused")
    assert main(["eval", "--data", str(packed), "--split", "val", "--methods", "input", "--count", "1"]) == 2


def test_pack_dataset_packs_only_the_splits_asked(full, tmp_path):
    out = tmp_path / "only_val"
    done = pack_dataset(full, out, splits=("val",))
    assert {p.parent.name for p in done} == {"val"} and not (out / "train").exists()
    with pytest.raises(InputError):
        pack_dataset(full, tmp_path / "none", splits=("test",))

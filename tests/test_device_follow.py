"""Every tensor follows the model's device: on a CUDA GPU a tensor made on the host (a factory without
`device=`, `torch.from_numpy` not moved, `.cpu()`) that meets one on the GPU stops the run with a device
mismatch. A CPU-only machine cannot see that, so these tests watch the whole of `complete` (coarse and full),
a drive tile and a few training steps of each stage on the CPU with `DeviceFollow`: each tensor is marked as on
the model's device (the models' parameters and buffers, factories given that device, `.to` it, and whatever an
op makes from such a tensor) or on the host (`torch.from_numpy`, factories without a device, `.cpu()`), and an
op that takes both, where CUDA would refuse it, is recorded with the line of hgca_core that made the call."""
from __future__ import annotations

import sys
import traceback
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten

from hgca_testdata import tiny_sample

ON, HOST = "device", "host"
TAG = "_hgca_where"
MOVES = {"to", "cuda", "cpu", "type_as"}
# ops CUDA runs with arguments on another device: copies between devices, and indexing with host indices
CROSSING = {"copy_", "__getitem__", "__setitem__", "index_put_", "index_put", "set_"}
FACTORIES = {"zeros", "ones", "empty", "full", "arange", "tensor", "as_tensor", "rand", "randn", "randint",
             "randperm", "linspace", "logspace", "eye", "zeros_like", "ones_like", "empty_like", "full_like",
             "rand_like", "randn_like", "randint_like", "new_zeros", "new_ones", "new_empty", "new_full",
             "new_tensor", "scalar_tensor", "tril_indices", "triu_indices", "sparse_coo_tensor", "asarray"}


def where(t: torch.Tensor) -> str | None:
    return getattr(t, TAG, None)


def mark(t, tag: str | None) -> None:
    if tag is None:
        return
    for x in tree_flatten(t)[0]:
        if isinstance(x, torch.Tensor):
            try:
                setattr(x, TAG, tag)
            except (AttributeError, RuntimeError):
                pass


def _caller() -> str:
    """The innermost line of hgca_core on the stack: where the mixing call was written."""
    for frame in reversed(traceback.extract_stack()[:-2]):
        if "/hgca_core/" in frame.filename:
            return f"{frame.filename.split('/hgca_core/')[-1]}:{frame.lineno} ({frame.line})"
    return "outside hgca_core"


class DeviceFollow(TorchFunctionMode):
    """Marks tensors as on the model's device or the host and records every op that would mix them on a GPU
    (0-dim host tensors excepted: CUDA takes those as scalars)."""

    def __init__(self, device: str = "cpu") -> None:
        super().__init__()
        self.device = torch.device(device)
        self.mixes: dict[str, str] = {}

    def _target(self, args, kwargs) -> str | None:
        """Where `.to(...)` sends its tensor: a device (or a tensor's), None for a dtype alone."""
        for a in (kwargs.get("device"), kwargs.get("other"), *args[1:]):
            if isinstance(a, torch.Tensor):
                return where(a)
            if isinstance(a, (str, torch.device)):
                return ON if torch.device(a).type == self.device.type else HOST
        return None

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        name = getattr(func, "__name__", "")
        inputs = [t for t in tree_flatten((args, kwargs))[0] if isinstance(t, torch.Tensor)]
        if name in MOVES:
            tag = HOST if name == "cpu" else ON if name == "cuda" else self._target(args, kwargs)
            mark(out, tag if tag is not None else where(args[0]))
            return out
        if name in FACTORIES and "device" in kwargs and kwargs["device"] is not None:
            mark(out, ON if torch.device(kwargs["device"]).type == self.device.type else HOST)
            return out
        if name in FACTORIES and not inputs:
            mark(out, HOST)
            return out
        checked = inputs if name not in CROSSING else [t for t in inputs[:1] if isinstance(t, torch.Tensor)]
        tags = {where(t) for t in checked if where(t) == ON or (where(t) == HOST and t.dim() > 0)}
        if tags == {ON, HOST}:
            self.mixes.setdefault(_caller(), name)
        tags = {where(t) for t in inputs}
        mark(out, ON if ON in tags else HOST if HOST in tags else None)
        return out


@pytest.fixture
def follow(monkeypatch):
    """A `DeviceFollow` over the test's body; `torch.from_numpy` gives host tensors (it bypasses modes)."""
    plain = torch.from_numpy

    def from_numpy(a):
        t = plain(a)
        mark(t, HOST)
        return t

    monkeypatch.setattr(torch, "from_numpy", from_numpy)
    for name, module in list(sys.modules.items()):    # constants made at import live on the host
        if name.startswith("hgca_core") and module is not None:
            for value in list(vars(module).values()):
                if isinstance(value, (torch.Tensor, tuple, list, dict)) and not isinstance(value, torch.nn.Parameter):
                    mark(value, HOST)
    mode = DeviceFollow("cpu")
    with mode:
        yield mode


def on_device(*modules: torch.nn.Module) -> None:
    for m in modules:
        for t in [*m.parameters(), *m.buffers()]:
            mark(t, ON)


def assert_no_mixes(mode: DeviceFollow) -> None:
    assert not mode.mixes, "host tensors meet the model's device:\n" + "\n".join(
        f"  {op} at {line}" for line, op in sorted(mode.mixes.items()))


@pytest.fixture(scope="module")
def fine_weights(tmp_path_factory) -> Path:
    from hgca_core.models.autoencoder import Autoencoder, AutoencoderConfig
    from hgca_core.models.cgca import CGCAConfig, CGCAKernel
    from hgca_core.training.export import save_weights

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("w") / "fine_small.pt"
    save_weights(path, CGCAKernel(CGCAConfig(channels=(8, 8, 8, 8, 8), steps=2)), {"stage": "test"},
                 autoencoder=Autoencoder(AutoencoderConfig()))
    return path


def test_the_mode_catches_a_host_tensor_meeting_the_model():
    mode = DeviceFollow("cpu")
    lin = torch.nn.Linear(3, 2)
    on_device(lin)
    with mode:
        lin(torch.zeros(4, 3, device="cpu")) + torch.ones(2)              # a factory's host tensor meets it
        moved = lin(torch.zeros(4, 3).to("cpu")) * torch.ones((), device="cpu")   # moved, and a scalar: fine
    assert list(mode.mixes.values()) == ["add"] and moved.shape == (4, 2)


@pytest.mark.parametrize("stage", ["coarse", "full"])
def test_complete_keeps_every_tensor_on_the_models_device(small_weights, fine_weights, stage, follow):
    from hgca_core.pipeline import complete, load_models
    from hgca_core.geometry.region import Region

    models = load_models(stage, small_weights, fine_weights if stage == "full" else None, "cpu")
    on_device(*(m for m in (models.coarse, models.fine, models.autoencoder) if m is not None))
    s = tiny_sample(3)
    pts = s["input_points"].astype(np.float64)
    region = Region(np.array([3.0, 3.0, 1.0]), np.array([6.0, 6.0, 4.0]), 0.0)
    out = complete(pts, region, origins=np.array([[3.0, 3.0, 2.0]]), stage=stage, weights=str(small_weights),
                   fine_weights=str(fine_weights) if stage == "full" else None, t1=2, t2=2, device="cpu")
    assert len(out) == 1
    assert_no_mixes(follow)


def test_a_drive_tile_keeps_every_tensor_on_the_models_device(small_weights, tmp_path, follow):
    sys.path.insert(0, str(Path(__file__).parent / "drive"))
    from drive_data import write_drive
    from hgca_core.models.weights import load_coarse
    from hgca_core.tiling.run import drive

    on_device(load_coarse(small_weights, "cpu")[0])
    files, poses = write_drive(tmp_path / "s", length=12.0)
    doc = drive(files, tmp_path / "d", poses=poses, size=12.8, overlap=3.2, stage="coarse", t1=2, threads=1,
                weights=str(small_weights), device="cpu")
    assert doc["status"] == "complete"
    assert_no_mixes(follow)


def test_training_steps_keep_every_tensor_on_the_models_device(tiny_dataset, tmp_path, follow, monkeypatch):
    from hgca_core.models.gca import GCAConfig
    from hgca_core.training import trainer
    from hgca_core.training.coarse import CoarseTask

    made = []
    build = trainer.EMA.__init__

    def remember(self, model, *a, **k):          # the trained model, however the trainer makes it
        on_device(model)
        made.append(model)
        build(self, model, *a, **k)

    monkeypatch.setattr(trainer.EMA, "__init__", remember)
    task = CoarseTask(str(tiny_dataset), GCAConfig(steps=3, channels=(8, 8, 16, 16, 16)), crop=24, val_count=1)
    trainer.train(task, tmp_path / "run", minutes=5, max_steps=2, batch=2, buffer_size=2, progress=False,
                  device="cpu")
    assert made
    assert_no_mixes(follow)


def test_fine_training_steps_keep_every_tensor_on_the_models_device(dataset, tmp_path, follow, monkeypatch):
    from scipy.spatial import cKDTree

    from hgca_core.models.autoencoder import Autoencoder, AutoencoderConfig
    from hgca_core.models.cgca import CGCAConfig
    from hgca_core.training.export import save_weights
    from hgca_core.training import trainer
    from hgca_core.training.fine import FineTask

    for split in ("train", "val"):                              # the fine stage also needs distance pairs
        for path in (dataset / split).glob("sample_*.npz"):
            s = dict(np.load(path))
            q = s["gt_surface"][::5] + np.random.default_rng(0).normal(0, 0.05, (len(s["gt_surface"][::5]), 3))
            q = q[np.all((q >= 0) & (q < [6.0, 6.0, 4.0]), axis=1)].astype(np.float32)
            s["udf_points"], s["udf_dist"] = q, cKDTree(s["gt_surface"]).query(q)[0].astype(np.float32)
            np.savez(path, **s)
    torch.manual_seed(0)
    save_weights(tmp_path / "ae.pt", Autoencoder(AutoencoderConfig(latent=4, enc_hidden=8, mlp_hidden=8,
                                                                   dec_channels=8)))
    build = trainer.EMA.__init__

    def remember(self, model, *a, **k):
        on_device(model)
        build(self, model, *a, **k)

    monkeypatch.setattr(trainer.EMA, "__init__", remember)
    cfg = CGCAConfig(latent=4, channels=(8, 8, 8), in_proj=8, pe_freq=1, crop=15, steps=2)
    task = FineTask(str(dataset), cfg, str(tmp_path / "ae.pt"), val_count=1)
    state = trainer.train(task, tmp_path / "fine", minutes=5, max_steps=2, batch=2, buffer_size=2, progress=False,
                          device="cpu")
    assert state["step"] == 2
    assert_no_mixes(follow)

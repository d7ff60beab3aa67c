"""The one weights module: round trips for every kind, the packaged files, and refusals that name the file and
say what it is (a pickle that would run code, the wrong kind of weights, a config that does not fit)."""
import hashlib
import os
import pickle

import pytest
import torch

from hgca_core.errors import InputError
from hgca_core.models.autoencoder import Autoencoder, AutoencoderConfig
from hgca_core.models.cgca import CGCAConfig, CGCAKernel
from hgca_core.models.gca import GCAConfig, GCAKernel
from hgca_core.models.semantics import SemanticHead, SemanticsConfig
from hgca_core.models.weights import KINDS, WEIGHTS_DIR, check_config, identify, load_autoencoder, load_coarse, load_file, load_fine, save_file, shipped
from hgca_core.training.export import save_weights

SMALL_AE = AutoencoderConfig(latent=4, enc_hidden=8, mlp_hidden=8, dec_channels=8)


class Payload:
    """Unpickling this runs `touch MARKER` (what a hostile weights file does)."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    torch.manual_seed(0)
    d = tmp_path_factory.mktemp("weights")
    coarse = GCAKernel(GCAConfig(channels=(8, 8, 16, 16, 16), steps=3))
    ae = Autoencoder(SMALL_AE)
    fine = CGCAKernel(CGCAConfig(latent=4, channels=(8, 8, 8, 8, 8), steps=2))
    return {"coarse": save_weights(d / "coarse.pt", coarse, {"note": "test"}),
            "autoencoder": save_weights(d / "ae.pt", ae),
            "fine": save_weights(d / "fine.pt", fine, autoencoder=ae),
            "models": {"coarse": coarse, "autoencoder": ae, "fine": fine}}


def _same_as_fp16(model: torch.nn.Module, loaded: torch.nn.Module) -> None:
    """Loaded float32 tensors are the saved fp16 values exactly; integer buffers are unchanged."""
    got = loaded.state_dict()
    for k, v in model.state_dict().items():
        want = v.half().float() if v.is_floating_point() else v
        assert got[k].dtype == want.dtype and torch.equal(got[k], want), k


def test_every_kind_round_trips(files):
    m = files["models"]
    coarse, meta = load_coarse(files["coarse"])
    _same_as_fp16(m["coarse"], coarse)
    assert meta == {"note": "test", "kind": "coarse"} and not coarse.training
    fine, ae, meta = load_fine(files["fine"])
    _same_as_fp16(m["fine"], fine)
    _same_as_fp16(m["autoencoder"], ae)
    assert meta["kind"] == "fine" and ae.cfg == SMALL_AE
    _same_as_fp16(m["autoencoder"], load_autoencoder(files["autoencoder"]))
    assert load_coarse(files["coarse"])[0] is coarse          # cached per file and device
    with pytest.raises(ValueError, match="autoencoder"):
        save_weights(files["fine"].parent / "x.pt", m["fine"])


def test_cache_sees_a_file_rewritten_in_place(tmp_path):
    path = tmp_path / "w.pt"
    save_weights(path, GCAKernel(GCAConfig(channels=(8, 8, 8, 8, 8), steps=3)))
    assert load_coarse(path)[0].cfg.steps == 3
    save_weights(path, GCAKernel(GCAConfig(channels=(8, 8, 8, 8, 8), steps=5)))
    assert load_coarse(path)[0].cfg.steps == 5


def test_packaged_files_are_plain_and_of_their_kind():
    """Every shipped file loads with weights_only=True, holds fp16 / integer tensors and is the kind its name says."""
    names = sorted(p.name for p in WEIGHTS_DIR.glob("*.pt"))
    assert names == ["autoencoder.pt", "coarse.pt", "coarse_noplanner.pt", "coarse_student.pt", "fine.pt",
                     "fine_student.pt", "semantics.pt"]
    for stage in ("coarse", "coarse-noplanner", "autoencoder", "fine", "semantics", "coarse-student", "fine-student"):
        blob = load_file(shipped(stage))
        assert identify(blob) == (stage.split("-")[0], False)
        assert all(v.dtype in (torch.float16, torch.int64) for v in blob["state_dict"].values())
    # the students are the teachers' networks on shorter chains
    assert load_coarse(shipped("coarse-student"))[0].cfg.steps == 10
    assert load_file(shipped("fine-student"))["config"]["steps"] == 5
    assert load_coarse(shipped("coarse-noplanner"))[0].planner is None
    assert load_coarse(shipped("coarse"))[0].planner is not None


@pytest.mark.parametrize("container", ["zip", "raw"])
def test_a_pickle_that_runs_code_is_refused_without_running(tmp_path, container):
    marker = tmp_path / "ran"
    path = tmp_path / "evil.pt"
    if container == "zip":   # a torch file whose config is a hostile object
        torch.save({"kind": "coarse", "config": Payload(str(marker)), "state_dict": {}, "meta": {}}, path)
    else:
        path.write_bytes(pickle.dumps(Payload(str(marker))))
    message = r"refused: it holds pickled Python objects \(posix\.system\)" if container == "zip" else "not a plain"
    for load in (load_file, load_coarse, load_fine, load_autoencoder):
        with pytest.raises(InputError, match=message + ".*; nothing from it was run") as err:
            load(path)
        assert str(err.value).startswith(str(path)) and "\n" not in str(err.value)
    assert not marker.exists()


def test_wrong_kind_says_what_the_file_is_and_which_option_takes_it(files, tmp_path):
    with pytest.raises(InputError, match=r"fine-stage weights .*--fine-weights`? takes; `hgca complete --weights` "
                                         r"takes coarse-stage weights"):
        load_coarse(files["fine"])
    with pytest.raises(InputError, match=r"autoencoder weights .*`hgca train fine --autoencoder` takes; "
                                         r"`hgca complete --weights`"):
        load_coarse(files["autoencoder"])
    with pytest.raises(InputError, match=r"coarse-stage weights .*`hgca complete --weights` takes; "
                                         r"`hgca complete --fine-weights` takes fine-stage"):
        load_fine(files["coarse"])
    with pytest.raises(InputError, match=r"fine-stage weights .* takes autoencoder weights"):
        load_autoencoder(files["fine"])
    ck = tmp_path / "ckpt.pt"
    save_file({"task": "fine", "model": {}, "config": {}}, ck)
    with pytest.raises(InputError, match=r"a fine training checkpoint \(`hgca train --export` turns it into"):
        load_fine(ck)
    save_file({"hello": torch.zeros(3)}, tmp_path / "other.pt")
    with pytest.raises(InputError, match="not an hgca weights file or training checkpoint"):
        load_coarse(tmp_path / "other.pt")
    save_file([torch.zeros(3)], tmp_path / "list.pt")
    with pytest.raises(InputError, match="holds a list"):
        load_coarse(tmp_path / "list.pt")


def test_configs_that_do_not_fit_the_tensors(files, tmp_path):
    blob = load_file(files["coarse"])
    cases = {"empty": ({**blob, "config": {}}, "config is empty"),
             "garbled": ({**blob, "config": {**blob["config"], "channels": [8, 16, 16, 16, 16]}},
                         r"tensors do not fit the coarse model the config describes: .*of another shape "
                         r"\(e\.g\. unet\.[^:]+: file \("),
             "nonsense": ({**blob, "config": {**blob["config"], "channels": "abc"}}, "does not describe a coarse model"),
             "threshold": ({**blob, "config": {**blob["config"], "keep": 1.0}},
                           r"does not describe a coarse model \(ValueError: keep must lie strictly between 0 and 1"),
             "missing": ({**blob, "state_dict": {k: v for i, (k, v) in enumerate(blob["state_dict"].items()) if i}},
                         r"1 missing \(e\.g\."),
             "not tensors": ({**blob, "state_dict": {"a": 1}}, "not a non-empty table of named tensors")}
    for name, (content, message) in cases.items():
        path = save_file(content, tmp_path / f"{name}.pt")
        with pytest.raises(InputError, match=message) as err:
            load_coarse(path)
        assert str(err.value).startswith(str(path)), name
    fine = load_file(files["fine"])
    path = save_file({**fine, "autoencoder": {**fine["autoencoder"], "config": {}}}, tmp_path / "fine_bad.pt")
    with pytest.raises(InputError, match="the autoencoder config is empty"):
        load_fine(path)
    path = save_file({k: v for k, v in fine.items() if k != "autoencoder"}, tmp_path / "fine_alone.pt")
    with pytest.raises(InputError, match="without their autoencoder"):
        load_fine(path)


def test_unreadable_files(tmp_path):
    for name, data in (("empty.pt", b""), ("text.pt", b"not a torch file at all"),):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(InputError, match="not a readable hgca weights file"):
            load_coarse(tmp_path / name)
    with pytest.raises(InputError, match=r"no such weights file \(train them with `hgca train fine"):
        load_fine(tmp_path / "nope.pt")
    with pytest.raises(InputError, match="is a folder"):
        load_coarse(tmp_path)
    good = save_weights(tmp_path / "cut.pt", GCAKernel(GCAConfig(channels=(8, 8, 8, 8, 8))))
    good.write_bytes(good.read_bytes()[:5000])
    with pytest.raises(InputError, match="not a readable hgca weights file"):
        load_coarse(good)


def test_kinds_table_covers_the_models():
    assert {k: (v.config, v.model) for k, v in KINDS.items()} == {
        "coarse": (GCAConfig, GCAKernel), "fine": (CGCAConfig, CGCAKernel),
        "autoencoder": (AutoencoderConfig, Autoencoder), "semantics": (SemanticsConfig, SemanticHead)}


def test_blend_interpolates_tensor_by_tensor_and_refuses_what_does_not_fit(files, tmp_path):
    from hgca_core.training.export import blend_files

    torch.manual_seed(1)
    other = GCAKernel(GCAConfig(channels=(8, 8, 16, 16, 16), steps=3))
    b = save_weights(tmp_path / "b.pt", other, {"steps": 7, "data": "d2"})
    a_sd, b_sd = load_file(files["coarse"])["state_dict"], load_file(b)["state_dict"]
    for t in (0.0, 0.5, 1.0):
        blob = blend_files(files["coarse"], b, t)
        floats = [k for k, v in a_sd.items() if v.is_floating_point()]
        assert floats and len(floats) < len(a_sd)          # the model has integer buffers to keep as they are
        for k, v in blob["state_dict"].items():
            want = ((1 - t) * a_sd[k].float() + t * b_sd[k].float()).half() if k in floats else a_sd[k]
            assert v.dtype == a_sd[k].dtype and torch.equal(v, want), (t, k)
        digest = hashlib.sha256(b.read_bytes()).hexdigest()   # the source named by content, not only by path
        assert blob["meta"]["blend"]["t"] == t and blob["meta"]["blend"]["b"] == {"file": str(b), "sha256": digest,
                                                                                   "steps": 7, "data": "d2"}
    mid = save_file(blend_files(files["coarse"], b, 0.5), tmp_path / "mid.pt")
    model, meta = load_coarse(mid)                           # a blend loads like any coarse weights
    assert meta["blend"]["a"]["file"] == str(files["coarse"])
    assert not torch.equal(model.state_dict()[floats[0]], load_coarse(b)[0].state_dict()[floats[0]])

    # a file written before a config field existed (the shipped coarse.pt has no `bias`) is the same architecture;
    # sampling settings come from the first file
    older = load_file(b)
    del older["config"]["bias"]
    older["config"]["keep"] = 0.4
    older = save_file(older, tmp_path / "older.pt")
    assert blend_files(files["coarse"], older, 0.5)["config"] == load_file(files["coarse"])["config"]
    assert blend_files(older, files["coarse"], 0.5)["config"]["keep"] == 0.4
    # a few-step student (b) blended back toward its teacher (a) samples the student's chain, not the teacher's
    student = load_file(b)
    student["config"].update(steps=2, alpha0=0.3, alpha1=0.02)
    student = save_file(student, tmp_path / "student.pt")
    blob = blend_files(files["coarse"], student, 0.7)
    assert {k: blob["config"][k] for k in ("steps", "alpha0", "alpha1")} == {"steps": 2, "alpha0": 0.3, "alpha1": 0.02}
    assert load_file(files["coarse"])["config"]["steps"] != 2
    assert load_coarse(save_file(blob, tmp_path / "sb.pt"))[0].cfg.steps == 2
    changed = load_file(b)
    changed["config"]["pe_axes"] = "x" if changed["config"]["pe_axes"] != "x" else "y"
    with pytest.raises(InputError, match="different architectures"):   # same tensor shapes, other meaning
        blend_files(files["coarse"], save_file(changed, tmp_path / "axes.pt"), 0.5)

    wider = save_weights(tmp_path / "w.pt", GCAKernel(GCAConfig(channels=(8, 8, 16, 16, 32), steps=3)))
    with pytest.raises(InputError, match="different architectures"):
        blend_files(files["coarse"], wider, 0.5)
    with pytest.raises(InputError, match="different architectures"):
        blend_files(files["coarse"], files["autoencoder"], 0.5)
    # fine weights blend over one autoencoder (a fine student keeps its teacher's), never over two
    fine_b = load_file(files["fine"])
    fine_b["state_dict"] = {k: v + 1 if v.is_floating_point() else v for k, v in fine_b["state_dict"].items()}
    fine_b["config"]["steps"] = 1
    fine_blob = blend_files(files["fine"], save_file(fine_b, tmp_path / "fine_b.pt"), 0.5)
    kept = load_file(files["fine"])["autoencoder"]
    assert fine_blob["autoencoder"]["config"] == kept["config"] and fine_blob["config"]["steps"] == 1
    assert all(torch.equal(v, kept["state_dict"][k]) for k, v in fine_blob["autoencoder"]["state_dict"].items())
    fine_mid, ae_mid, _ = load_fine(save_file(fine_blob, tmp_path / "fine_mid.pt"))
    name = next(k for k, v in fine_b["state_dict"].items() if v.is_floating_point())
    want = (load_file(files["fine"])["state_dict"][name].float() + 0.5).to(fine_b["state_dict"][name].dtype)
    assert torch.allclose(fine_mid.state_dict()[name].float(), want.float(), atol=1e-3)
    other_ae = load_file(files["fine"])
    other_ae["autoencoder"] = {**other_ae["autoencoder"], "state_dict": {
        k: v * 2 if v.is_floating_point() else v for k, v in other_ae["autoencoder"]["state_dict"].items()}}
    with pytest.raises(InputError, match="different autoencoders"):
        blend_files(files["fine"], save_file(other_ae, tmp_path / "other_ae.pt"), 0.5)
    ckpt = save_file({"task": "coarse", "model": a_sd, "config": {}}, tmp_path / "ckpt.pt")
    with pytest.raises(InputError, match="export a checkpoint"):
        blend_files(files["coarse"], ckpt, 0.5)
    with pytest.raises(ValueError, match="outside"):
        blend_files(files["coarse"], b, 1.5)


def test_config_values_of_the_wrong_type_or_out_of_bounds_are_refused_with_their_key(files, tmp_path):
    """Types come from the config dataclasses' defaults: a string where steps is a count, 10^9 steps (a run that
    would never end), a NaN rate, a float grid; every shipped file passes the same check."""
    blob = load_file(files["coarse"])
    bad = {"steps": "30", "blocks": 2.0, "use_planner": "yes", "alpha0": float("nan"), "grid": [192, 192, 0.5],
           "pe_axes": 3}
    for key, value in bad.items():
        path = save_file({**blob, "config": {**blob["config"], key: value}}, tmp_path / f"{key}.pt")
        with pytest.raises(InputError, match=f"its '{key}' must"):
            load_coarse(path)
    path = save_file({**blob, "config": {**blob["config"], "steps": 10**9}}, tmp_path / "long.pt")
    with pytest.raises(InputError, match="'steps' must be between 1 and 1000, got 1000000000"):
        load_coarse(path)
    for stage in ("coarse", "coarse-noplanner", "fine", "autoencoder"):
        shipped_blob = load_file(shipped(stage))
        kind = shipped_blob["kind"]
        check_config(shipped_blob["config"], kind, "", str(shipped(stage)))
        if "autoencoder" in shipped_blob:
            check_config(shipped_blob["autoencoder"]["config"], "autoencoder", "autoencoder ", str(shipped(stage)))


def test_non_finite_tensors_are_refused_at_load(files, tmp_path):
    """All-NaN weights gave an empty mesh and exit 0; one infinite value in the fine file's autoencoder is enough."""
    fine = load_file(files["fine"])
    name = next(iter(fine["autoencoder"]["state_dict"]))
    ae = {**fine["autoencoder"]["state_dict"]}
    ae[name] = ae[name].clone()
    ae[name].view(-1)[0] = float("inf")
    path = save_file({**fine, "autoencoder": {**fine["autoencoder"], "state_dict": ae}}, tmp_path / "inf.pt")
    with pytest.raises(InputError, match=f"autoencoder tensor '{name}' holds 1 NaN or infinite value"):
        load_fine(path)

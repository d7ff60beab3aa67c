"""Sparse conv layers against dense torch convolutions, autograd, batching, determinism, map caching."""
from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from hgca_core.geometry.coords import pack, unique
from hgca_core.nn import conv as conv_mod
from hgca_core.nn.conv import SparseConvFunction
from hgca_core.nn.kernel_map import downsample_map, submanifold_map, submanifold_map_reference, upsample_map
from hgca_core.nn.sparse import SparseBatchNorm, SparseConv3d, SparseConvTranspose3d, SparseTensor, SubMConv3d, sparse_cat


def random_coords(gen: torch.Generator, batch: int, size: int, p: float, stride: int = 1) -> torch.Tensor:
    """Random active cells of a batch x size^3 grid (grid units), scaled to finest units by `stride`."""
    occ = torch.rand((batch, size, size, size), generator=gen) < p
    c = occ.nonzero()
    c[:, 1:] *= stride
    return unique(c)


def to_dense(x: SparseTensor, batch: int, size: int) -> torch.Tensor:
    """(B, C, S, S, S) grid in the tensor's own units (coords / stride); inactive cells are zero."""
    d = x.feats.new_zeros((batch, x.num_channels, size, size, size))
    c = x.coords.clone()
    c[:, 1:] //= x.stride
    d[c[:, 0], :, c[:, 1], c[:, 2], c[:, 3]] = x.feats
    return d


def at(dense: torch.Tensor, coords: torch.Tensor, stride: int) -> torch.Tensor:
    c = coords.clone()
    c[:, 1:] //= stride
    return dense[c[:, 0], :, c[:, 1], c[:, 2], c[:, 3]]


def dense_subm_weight(w: torch.Tensor, k: int) -> torch.Tensor:
    """(K, cin, cout) -> conv3d weight (cout, cin, k, k, k) under the documented offset order."""
    return w.permute(2, 1, 0).reshape(w.shape[2], w.shape[1], k, k, k)


@pytest.fixture
def gen() -> torch.Generator:
    return torch.Generator().manual_seed(0)


@pytest.fixture(params=["table", "pairs"])
def path(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Run a test on both ways of executing a map (output-stationary table, and pair list + scatter)."""
    monkeypatch.setattr(conv_mod, "TABLE_MIN_DENSITY", 0.0 if request.param == "table" else 2.0)
    return request.param


@pytest.mark.parametrize("stride", [1, 2])
@pytest.mark.parametrize("kernel", [3, 5])
def test_submconv_matches_dense(path: str, gen: torch.Generator, stride: int, kernel: int) -> None:
    size, cin, cout = 9, 3, 4
    coords = random_coords(gen, 2, size, 0.3, stride)
    x = SparseTensor(coords, torch.randn(len(coords), cin, generator=gen, dtype=torch.float64), stride)
    conv = SubMConv3d(cin, cout, kernel, bias=True).double()
    with torch.no_grad():
        conv.bias.normal_(generator=gen)
    y = conv(x)
    assert y.coords is x.coords and y.stride == stride
    ref = F.conv3d(to_dense(x, 2, size), dense_subm_weight(conv.weight, kernel), conv.bias, padding=kernel // 2)
    torch.testing.assert_close(y.feats, at(ref, coords, stride), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("stride", [1, 2])
def test_strided_conv_matches_dense(path: str, gen: torch.Generator, stride: int) -> None:
    size, cin, cout = 10, 3, 5
    coords = random_coords(gen, 2, size, 0.25, stride)
    x = SparseTensor(coords, torch.randn(len(coords), cin, generator=gen, dtype=torch.float64), stride)
    conv = SparseConv3d(cin, cout, 2, 2).double()
    y = conv(x)
    assert y.stride == 2 * stride
    SparseTensor(y.coords, y.feats, y.stride)                   # sorted, unique, aligned to the stride
    expect = unique(torch.cat([coords[:, :1], coords[:, 1:] // (2 * stride) * (2 * stride)], 1))
    assert torch.equal(y.coords, expect)
    w = conv.weight.permute(2, 1, 0).reshape(cout, cin, 2, 2, 2)
    ref = F.conv3d(to_dense(x, 2, size), w, stride=2)
    torch.testing.assert_close(y.feats, at(ref, y.coords, y.stride), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("from_down", [False, True])
def test_transposed_conv_matches_dense(path: str, gen: torch.Generator, from_down: bool) -> None:
    size, cin, cout = 10, 4, 3
    fine = random_coords(gen, 2, size, 0.3)
    if from_down:   # decoder case: the coarse set is the downsampled target, map comes from the cache
        src = SparseTensor(fine, torch.zeros(len(fine), 1, dtype=torch.float64))
        coarse = SparseConv3d(1, 1).double()(src)
        x = SparseTensor(coarse.coords, torch.randn(len(coarse), cin, generator=gen, dtype=torch.float64),
                         2, cache=src.cache, check=False)
        target = src
    else:           # arbitrary coarse set: some target cells have no parent and must get zeros
        coarse_c = random_coords(gen, 2, size // 2, 0.5, 2)
        x = SparseTensor(coarse_c, torch.randn(len(coarse_c), cin, generator=gen, dtype=torch.float64), 2)
        target = SparseTensor(fine, torch.zeros(len(fine), 1, dtype=torch.float64))
    conv = SparseConvTranspose3d(cin, cout, 2, 2).double()
    y = conv(x, target)
    assert y.coords is target.coords and y.stride == 1
    w = conv.weight.permute(1, 2, 0).reshape(cin, cout, 2, 2, 2)
    ref = F.conv_transpose3d(to_dense(x, 2, size // 2), w, stride=2)
    torch.testing.assert_close(y.feats, at(ref, fine, 1), rtol=1e-10, atol=1e-10)
    if not from_down:
        assert (y.feats.abs().sum(1) == 0).any()                # orphans exist and are zero


@pytest.mark.parametrize("kernel,stride", [(3, 1), (3, 4), (5, 2), (7, 1)])
def test_fast_submanifold_map_equals_reference(gen: torch.Generator, kernel: int, stride: int) -> None:
    """Column-wise search (few queries) gives exactly the pairs of the all-offsets search."""
    for p in (0.05, 0.4, 0.95):
        c = random_coords(gen, 2, 10, p, stride)
        c[:, 1:] -= 5 * stride                                  # negative coordinates too
        keys = pack(unique(c))
        a, b = submanifold_map(keys, kernel, stride), submanifold_map_reference(keys, kernel, stride)
        assert a.splits == b.splits and a.identity == b.identity == kernel ** 3 // 2
        assert torch.equal(a.in_idx, b.in_idx) and torch.equal(a.out_idx, b.out_idx)


def test_batches_do_not_mix(path: str, gen: torch.Generator) -> None:
    """Sample 1 alone gives the same features as sample 1 next to a different sample 0."""
    c1 = random_coords(gen, 1, 8, 0.4)
    c0 = random_coords(gen, 1, 8, 0.4)
    c1b = c1.clone()
    c1b[:, 0] = 1
    f1 = torch.randn(len(c1), 3, generator=gen, dtype=torch.float64)
    f0 = torch.randn(len(c0), 3, generator=gen, dtype=torch.float64)
    both = SparseTensor(torch.cat([c0, c1b]), torch.cat([f0, f1]))
    alone = SparseTensor(c1, f1)
    sub, down = SubMConv3d(3, 4).double(), SparseConv3d(3, 4).double()
    up = SparseConvTranspose3d(4, 2).double()
    for layer_out in (lambda t: sub(t), lambda t: up(down(t), t)):
        yb, ya = layer_out(both), layer_out(alone)
        torch.testing.assert_close(yb.feats[len(c0):], ya.feats, rtol=0, atol=1e-12)
    db, da = down(both), down(alone)
    m = db.coords[:, 0] == 1
    assert torch.equal(db.coords[m][:, 1:], da.coords[:, 1:])


def _gradcheck_layer(fn, feats: torch.Tensor, weight: torch.Tensor) -> None:
    assert torch.autograd.gradcheck(fn, (feats, weight), eps=1e-6, atol=1e-8)


def test_gradcheck_submconv(path: str, gen: torch.Generator) -> None:
    coords = random_coords(gen, 2, 3, 0.5)
    kmap = submanifold_map(pack(coords), 3, 1)
    f = torch.randn(len(coords), 2, generator=gen, dtype=torch.float64, requires_grad=True)
    w = torch.randn(27, 2, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    _gradcheck_layer(lambda a, b: SparseConvFunction.apply(a, b, kmap), f, w)


def test_gradcheck_strided_and_transposed(path: str, gen: torch.Generator) -> None:
    coords = random_coords(gen, 2, 4, 0.5)
    out_c, kmap = downsample_map(coords, 1, 2)
    f = torch.randn(len(coords), 2, generator=gen, dtype=torch.float64, requires_grad=True)
    w = torch.randn(8, 2, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    _gradcheck_layer(lambda a, b: SparseConvFunction.apply(a, b, kmap), f, w)
    coarse = random_coords(gen, 2, 2, 0.6, 2)
    upmap = upsample_map(pack(coarse), coords, 1, 2)
    g = torch.randn(len(coarse), 2, generator=gen, dtype=torch.float64, requires_grad=True)
    _gradcheck_layer(lambda a, b: SparseConvFunction.apply(a, b, upmap), g, w)


def test_layer_gradients_match_dense(path: str, gen: torch.Generator) -> None:
    """Gradients through the modules (bias included) equal those of the dense reference."""
    size = 6
    coords = random_coords(gen, 1, size, 0.4)
    f = torch.randn(len(coords), 2, generator=gen, dtype=torch.float64, requires_grad=True)
    conv = SubMConv3d(2, 3, bias=True).double()
    y = conv(SparseTensor(coords, f))
    (y.feats ** 2).sum().backward()
    fd = f.detach().clone().requires_grad_(True)
    wd = dense_subm_weight(conv.weight.detach(), 3).clone().requires_grad_(True)
    bd = conv.bias.detach().clone().requires_grad_(True)
    idx = (coords[:, 0], coords[:, 1], coords[:, 2], coords[:, 3])
    dense_in = torch.zeros((1, size, size, size, 2), dtype=torch.float64).index_put(idx, fd).permute(0, 4, 1, 2, 3)
    ref = F.conv3d(dense_in, wd, bd, padding=1).permute(0, 2, 3, 4, 1)[idx]
    (ref ** 2).sum().backward()
    torch.testing.assert_close(f.grad, fd.grad)
    torch.testing.assert_close(conv.weight.grad, wd.grad.reshape(3, 2, 27).permute(2, 1, 0))
    torch.testing.assert_close(conv.bias.grad, bd.grad)


def _run_all(threads: int, coords: torch.Tensor, feats: torch.Tensor, seed: int) -> list[torch.Tensor]:
    prev = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        torch.manual_seed(seed)
        sub, down, up = SubMConv3d(16, 16), SparseConv3d(16, 24), SparseConvTranspose3d(24, 16)
        f = feats.clone().requires_grad_(True)
        x = SparseTensor(coords, f)
        y = up(down(sub(x)), x)
        (y.feats * torch.linspace(-1, 1, y.feats.numel()).view_as(y.feats)).sum().backward()
        return [y.feats.detach(), f.grad, sub.weight.grad, down.weight.grad, up.weight.grad]
    finally:
        torch.set_num_threads(prev)


def test_bit_identical_across_thread_counts(path: str, gen: torch.Generator, monkeypatch: pytest.MonkeyPatch) -> None:
    """1 vs 2 threads give bit-identical forward and backward (with several chunks per map)."""
    monkeypatch.setattr(conv_mod, "CHUNK_ELEMENTS", 1 << 14)
    monkeypatch.setattr(conv_mod, "TABLE_CHUNK_ELEMENTS", 1 << 14)
    coords = random_coords(gen, 2, 24, 0.15)
    feats = torch.randn(len(coords), 16, generator=gen)
    a = _run_all(1, coords, feats, 3)
    b = _run_all(2, coords, feats, 3)
    for u, v in zip(a, b):
        assert torch.equal(u, v)


def test_chunking_does_not_change_results(path: str, gen: torch.Generator, monkeypatch: pytest.MonkeyPatch) -> None:
    coords = random_coords(gen, 1, 12, 0.3)
    f = torch.randn(len(coords), 4, generator=gen, dtype=torch.float64)
    conv = SubMConv3d(4, 4).double()
    ref = conv(SparseTensor(coords, f)).feats
    monkeypatch.setattr(conv_mod, "CHUNK_ELEMENTS", 7)
    monkeypatch.setattr(conv_mod, "TABLE_CHUNK_ELEMENTS", 7 * 27 * 4)
    torch.testing.assert_close(conv(SparseTensor(coords, f)).feats, ref, rtol=1e-12, atol=1e-12)


def test_kernel_maps_are_cached_and_shared(gen: torch.Generator) -> None:
    coords = random_coords(gen, 1, 8, 0.3)
    x = SparseTensor(coords, torch.randn(len(coords), 4, generator=gen))
    a, b = SubMConv3d(4, 4), SubMConv3d(4, 4)
    y = a(x)
    kmap = x.cache[("subm", 1, 3)][1]
    b(y)
    assert x.cache[("subm", 1, 3)][1] is kmap                   # second layer reused it
    d1, d2 = SparseConv3d(4, 8), SparseConv3d(4, 8)
    assert d1(x).coords is d2(y).coords                         # same coarse coords object -> same maps
    up = SparseConvTranspose3d(8, 4)(d1(x), x)
    assert up.cache is x.cache
    assert x.cache[("up", 2, 2)][1].in_idx is x.cache[("down", 1, 2)][1][1].out_idx   # reused, transposed
    other = random_coords(gen, 1, 8, 0.3)
    assert SparseTensor(other, torch.zeros(len(other), 4)).cache is not x.cache


def test_stale_cache_entry_is_rebuilt(gen: torch.Generator) -> None:
    """A cache shared with a tensor on different coords must not hand out the wrong map."""
    c1, c2 = random_coords(gen, 1, 6, 0.4), random_coords(gen, 1, 6, 0.4)
    conv = SubMConv3d(2, 2).double()
    x1 = SparseTensor(c1, torch.randn(len(c1), 2, dtype=torch.float64))
    conv(x1)
    x2 = SparseTensor(c2, torch.randn(len(c2), 2, dtype=torch.float64), cache=x1.cache)
    fresh = SparseTensor(c2, x2.feats)
    torch.testing.assert_close(conv(x2).feats, conv(fresh).feats)


def test_sparse_tensor_validation_and_helpers(gen: torch.Generator) -> None:
    c = torch.tensor([[0, 1, 1, 1], [0, 0, 0, 0]])
    with pytest.raises(ValueError, match="sorted"):
        SparseTensor(c, torch.zeros(2, 1))
    with pytest.raises(ValueError, match="multiples"):
        SparseTensor(c.flip(0), torch.zeros(2, 1), stride=2)
    with pytest.raises(ValueError, match="feats"):
        SparseTensor(c.flip(0), torch.zeros(3, 1))
    x = SparseTensor.from_points(torch.tensor([[0, 1, 1, 1], [0, 0, 0, 0], [0, 1, 1, 1]]),
                                 torch.tensor([[1.0], [2.0], [3.0]]))
    assert torch.equal(x.coords, c.flip(0)) and torch.equal(x.feats, torch.tensor([[2.0], [2.0]]))
    y = sparse_cat(x, x.replace_feats(x.feats * 2))
    assert y.num_channels == 2 and y.cache is x.cache
    with pytest.raises(ValueError, match="share coords"):
        sparse_cat(x, SparseTensor(torch.tensor([[0, 0, 0, 0], [0, 0, 0, 1]]), torch.zeros(2, 1)))
    assert x.to(torch.float64).dtype == torch.float64 and x.to(torch.float64).coords.dtype == torch.int64


def test_norms(gen: torch.Generator) -> None:
    coords = random_coords(gen, 2, 6, 0.5)
    f = torch.randn(len(coords), 3, generator=gen) * 5 + 2
    x = SparseTensor(coords, f)
    z = SparseBatchNorm(3)(x).feats
    torch.testing.assert_close(z.mean(0), torch.zeros(3), atol=1e-5, rtol=0)
    torch.testing.assert_close(z.var(0, unbiased=False), torch.ones(3), atol=1e-3, rtol=0)


def test_inplace_norm_at_inference_is_batchnorm1d_bit_for_bit(gen: torch.Generator) -> None:
    """`inplace` norms overwrite their input only at inference (eval, no autograd), with BatchNorm1d's exact result;
    in training mode or with gradients on they leave it alone."""
    coords = random_coords(gen, 2, 6, 0.5)
    f = torch.randn(len(coords), 3, generator=gen) * 5 + 2
    norm = SparseBatchNorm(3, inplace=True)
    with torch.no_grad():
        norm.bn.running_mean.copy_(torch.tensor([1.0, -2.0, 0.5]))
        norm.bn.running_var.copy_(torch.tensor([4.0, 0.3, 2.0]))
        norm.bn.weight.copy_(torch.tensor([0.7, 1.3, -0.2]))
        norm.bn.bias.copy_(torch.tensor([0.1, 0.0, 3.0]))
    want = norm.eval().bn(f)
    x = SparseTensor(coords, f.clone())
    with torch.no_grad():
        y = norm(x)
    assert y.feats.data_ptr() == x.feats.data_ptr() and torch.equal(y.feats, want)
    for train, grad in ((False, True), (True, False)):
        x = SparseTensor(coords, f.clone())
        norm.train(train)
        with torch.set_grad_enabled(grad):
            y = norm(x)
        assert torch.equal(x.feats, f) and y.feats.data_ptr() != x.feats.data_ptr()


def test_empty_input(path: str) -> None:
    x = SparseTensor(torch.zeros((0, 4), dtype=torch.long), torch.zeros(0, 3))
    y = SubMConv3d(3, 4)(x)
    d = SparseConv3d(3, 4)(x)
    u = SparseConvTranspose3d(4, 2)(d, x)
    assert y.feats.shape == (0, 4) and d.feats.shape == (0, 4) and u.feats.shape == (0, 2)


def test_bf16_gemms_for_inference_only(gen: torch.Generator, path: str) -> None:
    """gemm_precision(bf16) changes no-grad convs by ~bf16 rounding, leaves training (grad) convs exact, and is
    deterministic across thread counts."""
    from hgca_core.nn.conv import gemm_precision, resolve_precision

    coords = random_coords(gen, 1, 20, 0.3)
    feats = torch.randn(len(coords), 16, generator=gen)
    sub, down, up = SubMConv3d(16, 16), SparseConv3d(16, 24), SparseConvTranspose3d(24, 16)

    def run(threads: int | None = None) -> torch.Tensor:
        prev = torch.get_num_threads()
        torch.set_num_threads(threads or prev)
        try:
            x = SparseTensor(coords, feats)
            return up(down(sub(x)), x).feats
        finally:
            torch.set_num_threads(prev)

    with torch.no_grad():
        ref = run()
        with gemm_precision(torch.bfloat16):
            low, low1, low2 = run(), run(1), run(2)
    assert not torch.equal(low, ref)                                        # the bf16 path ran
    assert (low - ref).abs().max() < 0.02 * ref.abs().max()                 # ... at bf16 accuracy
    assert torch.equal(low1, low2) and low.dtype == torch.float32
    with gemm_precision(torch.bfloat16):
        trained = run()                                                     # weights need grads: full precision
    assert torch.equal(trained.detach(), ref)
    assert resolve_precision("fp32") is None and resolve_precision("bf16") is torch.bfloat16
    import argparse

    from hgca_core.commands.arguments import add_config_arguments
    from hgca_core.nn.conv import PRECISIONS, precision_name

    parser = argparse.ArgumentParser()
    add_config_arguments(parser, ("precision",))
    assert tuple(parser._option_string_actions["--precision"].choices) == PRECISIONS   # the CLI spells them out
    assert [precision_name(resolve_precision(n)) for n in ("fp32", "bf16")] == ["fp32", "bf16"]
    with pytest.raises(ValueError, match="precision"):
        resolve_precision("fp8")


def test_bf16_training_gemms(gen: torch.Generator, path: str) -> None:
    """training_precision(bf16): forward and both backward GEMMs in bf16, so outputs and gradients differ from
    float32 by bf16 rounding only; gradients and weights stay float32; outside the block training is exact."""
    from hgca_core.nn.conv import training_precision

    coords = random_coords(gen, 1, 20, 0.3)
    feats = torch.randn(len(coords), 16, generator=gen)
    layers = torch.nn.ModuleList([SubMConv3d(16, 16), SparseConv3d(16, 24), SparseConvTranspose3d(24, 16)])

    def grads() -> tuple[torch.Tensor, list[torch.Tensor], torch.Tensor]:
        layers.zero_grad(set_to_none=True)
        f = feats.clone().requires_grad_(True)
        x = SparseTensor(coords, f)
        out = layers[2](layers[1](layers[0](x)), x).feats
        (out ** 2).sum().backward()
        return out.detach(), [p.grad.clone() for p in layers.parameters() if p.grad is not None], f.grad.clone()

    ref_out, ref_w, ref_in = grads()
    with training_precision(torch.bfloat16):
        out, gw, gin = grads()
    again = grads()
    assert torch.equal(again[0], ref_out) and torch.equal(again[2], ref_in)       # the block ends cleanly
    assert not torch.equal(out, ref_out) and not torch.equal(gin, ref_in)          # the bf16 path ran
    assert out.dtype == gin.dtype == torch.float32 and all(g.dtype == torch.float32 for g in gw)

    def rel(a: torch.Tensor, b: torch.Tensor) -> float:
        return float((a - b).norm() / b.norm())

    assert rel(out, ref_out) < 0.01 and rel(gin, ref_in) < 0.02
    assert len(gw) == len(ref_w) and max(rel(a, b) for a, b in zip(gw, ref_w)) < 0.02

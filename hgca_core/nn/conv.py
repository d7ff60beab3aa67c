"""Gather-GEMM-scatter sparse convolution (pure PyTorch).

Two ways to run a `KernelMap`, both in a fixed order, so the result does not depend on the thread count
(the CPU build of spconv gets exactly this wrong). Inside a GEMM, MKL splits the reduction by thread count
unless its strict reproducibility mode is on (`MKL_CBWR=AUTO,STRICT`, which `import hgca_core` sets before any
BLAS call): with it, the weight gradients (a reduction over every row) are bit-identical on 1 and 2 threads.

* dense maps (the finest level of the coarse U-Net fills ~78% of its (output, offset) slots):
  output-stationary. Per chunk of output rows, one `index_select` gathers every offset's input row (a zero
  row where there is none) into an (n, K * cin) block and one GEMM with the (K * cin, cout) weight writes the
  output rows. No scatter (torch's CPU `index_add_` costs ~70 ns a row and runs on one thread), one large
  GEMM instead of K small ones, at the price of multiplying the empty slots' zeros. The adjoint of a
  submanifold map is the same table with the offsets reversed, so its input gradient runs the same way.
* sparse maps (transposed convs, whose outputs have one pair each): the pair list cut into chunks, one
  `index_select` of the input rows, one GEMM per offset, one `index_add_` into the output.

Inference may run the GEMMs in bfloat16 (`gemm_precision`): inputs and weights are rounded to bf16, products
accumulate in float32 inside the GEMM, outputs and everything between convolutions stay float32. On a CPU with
AVX512-BF16 that makes the finest-level convs ~2.8x faster at ~0.3% relative error per conv. Training takes
its own setting (`training_precision`, `hgca train --precision bf16`): the forward and both backward GEMMs in
bf16 with float32 accumulation inside each GEMM, the sums across chunks, the weights, their gradients and the
optimiser state in float32 (mixed precision as `torch.autocast` does it, for our custom op).
"""
from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator

import torch
from torch.autograd.function import once_differentiable

from hgca_core.nn.kernel_map import TABLE_MIN_DENSITY, KernelMap  # noqa: F401  (the threshold, re-exported)
from hgca_core.nn.precision import DEFAULT_PRECISION, PRECISIONS  # noqa: F401  (re-exported)

# Elements (rows x channels) gathered per chunk: big enough that GEMMs amortise the per-call
# overhead, small enough that the chunk buffers stay in cache-friendly sizes and memory stays bounded.
CHUNK_ELEMENTS = 1 << 20


# MKL (torch 2.13, AVX-512) takes a thread-count-dependent path for GEMMs with 5-11 rows, so results
# change in the last bit between 1 and 2 threads. GEMMs with fewer rows than this are zero-padded.
MIN_GEMM_ROWS = 16


def _rows(cin: int, cout: int) -> int:
    return max(1, CHUNK_ELEMENTS // max(cin, cout, 1))


def _mm(a: torch.Tensor, b: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """a @ b (into `out`), bit-identical whatever the thread count (see MIN_GEMM_ROWS)."""
    n = a.shape[0]
    if n >= MIN_GEMM_ROWS or n == 0:
        return torch.mm(a, b) if out is None else torch.mm(a, b, out=out)
    pad = a.new_zeros((MIN_GEMM_ROWS, a.shape[1]))
    pad[:n] = a
    res = torch.mm(pad, b)[:n]
    return res if out is None else out.copy_(res)


# Elements gathered per chunk on the table path (n rows x K * cin): 2 MB of float32, so the GEMM reads the block
# the gather just wrote from cache. Rows are independent, so the chunk size does not change a bit of the output;
# 16 MB chunks cost ~10 % more CPU time per coarse and fine step (1 thread, the default region).
TABLE_CHUNK_ELEMENTS = 1 << 19
# The weight gradient sums its chunks' products in turn, so its chunk size sets the order of that sum: it keeps the
# 16 MB chunks its results were made with.
TABLE_GRAD_CHUNK_ELEMENTS = 1 << 22


# GEMM dtype of the convolutions that need no gradients (inference) and of those that do (training); None: as
# the features. Set for a block by `gemm_precision` / `training_precision`.
_GEMM_DTYPE: dict[bool, torch.dtype | None] = {False: None, True: None}


@contextmanager
def _gemm_dtype_scope(training: bool, dtype: torch.dtype | None) -> Iterator[None]:
    saved, _GEMM_DTYPE[training] = _GEMM_DTYPE[training], dtype
    try:
        yield
    finally:
        _GEMM_DTYPE[training] = saved


def gemm_precision(dtype: torch.dtype | None):
    """Within the block, convolutions that need no gradients run their GEMMs in `dtype` (None: as the features)."""
    return _gemm_dtype_scope(False, dtype)


def training_precision(dtype: torch.dtype | None):
    """Within the block, convolutions that need gradients run their forward and backward GEMMs in `dtype`."""
    return _gemm_dtype_scope(True, dtype)


def resolve_precision(name: str, device: str = "cpu") -> torch.dtype | None:
    """GEMM dtype for inference: 'fp32' -> None (full precision), 'bf16' -> bfloat16, 'auto' -> bfloat16 where
    the hardware does it natively (CPUs with AVX512-BF16 / AMX, CUDA GPUs with bf16 support), else None."""
    if name not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, not {name!r}")
    if name == "auto":
        if str(device).startswith("cuda"):
            native = torch.cuda.is_available() and torch.cuda.is_bf16_supported()
        else:
            native = bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
        name = "bf16" if native else "fp32"
    return torch.bfloat16 if name == "bf16" else None


def precision_name(dtype: torch.dtype | None) -> str:
    """The name `resolve_precision` maps to `dtype` (for result files)."""
    return "bf16" if dtype == torch.bfloat16 else "fp32"


def _table_blocks(feats: torch.Tensor, table: torch.Tensor, dtype: torch.dtype,
                  chunk: int | None = None) -> Iterator[tuple[int, int, torch.Tensor]]:
    """(r0, r1, block): for each chunk of table rows, every offset's input row side by side, an (r1 - r0, K * cin)
    block in `dtype`, with zeros where the table says none (row len(feats)). The block's buffer is reused."""
    n_out, kvol = table.shape
    cin = feats.shape[1]
    padded = feats.new_empty((len(feats) + 1, cin), dtype=dtype)   # one copy (and cast) of the features + a zero row
    padded[:-1] = feats
    padded[-1] = 0
    rows = max(1, (chunk or TABLE_CHUNK_ELEMENTS) // (kvol * cin))
    buf = padded.new_empty((min(rows, n_out) * kvol, cin))
    for r0 in range(0, n_out, rows):
        r1 = min(n_out, r0 + rows)
        g = torch.index_select(padded, 0, table[r0:r1].reshape(-1), out=buf[:(r1 - r0) * kvol])
        yield r0, r1, g.view(r1 - r0, kvol * cin)


def table_gemm(feats: torch.Tensor, weight: torch.Tensor, table: torch.Tensor,
               dtype: torch.dtype | None = None) -> torch.Tensor:
    """out[o] = sum_k feats[table[o, k]] @ weight[k], where row len(feats) of `table` means none; GEMMs in
    `dtype` (default: the features'), output in the features' dtype."""
    kvol, cin, cout = weight.shape
    dt = dtype or feats.dtype
    out = feats.new_empty((table.shape[0], cout))
    w2 = weight.reshape(kvol * cin, cout).to(dt)
    for r0, r1, block in _table_blocks(feats, table, dt):
        if dt == out.dtype:
            _mm(block, w2, out=out[r0:r1])
        else:
            out[r0:r1] = _mm(block, w2)
    return out


def table_weight_grad(feats: torch.Tensor, grad_out: torch.Tensor, table: torch.Tensor, kvol: int,
                      dtype: torch.dtype | None = None) -> torch.Tensor:
    """grad_W[k] = sum_o feats[table[o, k]].T @ grad_out[o], chunk by chunk, as (K, cin, cout); GEMMs in `dtype`
    (default: the features'), the sum over chunks in the features' dtype."""
    cin, cout = feats.shape[1], grad_out.shape[1]
    dt = dtype or feats.dtype
    grad = feats.new_zeros((kvol * cin, cout))
    for r0, r1, block in _table_blocks(feats, table, dt, TABLE_GRAD_CHUNK_ELEMENTS):
        if dt == grad.dtype:
            grad.addmm_(block.T, grad_out[r0:r1])
        else:
            grad += torch.mm(block.T, grad_out[r0:r1].to(dt)).to(grad.dtype)
    return grad.view(kvol, cin, cout)


def gemm_forward(feats: torch.Tensor, weight: torch.Tensor, kmap: KernelMap,
                 dtype: torch.dtype | None = None) -> torch.Tensor:
    """out[o] = sum over pairs (i, o, k) of feats[i] @ weight[k]; no autograd. GEMMs in `dtype` (default: the
    features'), sums and output in the features' dtype."""
    kvol, cin, cout = weight.shape
    if kvol > 1 and kmap.density >= TABLE_MIN_DENSITY:
        return table_gemm(feats, weight, kmap.table, dtype)
    dt = dtype or feats.dtype
    f, w = feats.to(dt), weight.to(dt)
    if kmap.identity is not None:
        out = _mm(f, w[kmap.identity]).to(feats.dtype)
    else:
        out = feats.new_zeros((kmap.n_out, cout))
    rows = _rows(cin, cout)
    chunks = kmap.chunks(rows)
    if chunks:
        # one pair of buffers reused by every chunk: fresh multi-MB tensors cost page faults each time
        rows = max(r1 - r0 for r0, r1, _ in chunks)
        gbuf, pbuf = f.new_empty((rows, cin)), f.new_empty((rows, cout))
    for r0, r1, pieces in chunks:
        g = torch.index_select(f, 0, kmap.in_idx[r0:r1], out=gbuf[:r1 - r0])
        prod = pbuf[:r1 - r0]
        for k, a, b in pieces:
            _mm(g[a:b], w[k], out=prod[a:b])
        out.index_add_(0, kmap.out_idx[r0:r1], prod.to(out.dtype))
    return out


def gemm_backward(feats: torch.Tensor, weight: torch.Tensor, kmap: KernelMap, grad_out: torch.Tensor,
                  need_feats: bool, need_weight: bool, dtype: torch.dtype | None = None
                  ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """grad_in[i] += grad_out[o] @ W[k].T and grad_W[k] = sum feats[i].T @ grad_out[o] over pairs; GEMMs in
    `dtype` (default: the features'), sums and gradients in the features' dtype."""
    kvol, cin, cout = weight.shape
    grad_out = grad_out.contiguous()
    grad_in = grad_w = None
    if kvol > 1 and kmap.symmetric and kmap.density >= TABLE_MIN_DENSITY:
        table = kmap.table
        if need_feats:  # adjoint of a submanifold map: table[i, j] = o pairs (i -> o) under offset K-1-j
            grad_in = table_gemm(grad_out, weight.flip(0).transpose(1, 2).contiguous(), table, dtype)
        if need_weight:
            grad_w = table_weight_grad(feats, grad_out, table, kvol, dtype)
        return grad_in, grad_w
    dt = dtype or feats.dtype
    f_dt, go_dt, w_dt = feats.to(dt), grad_out.to(dt), weight.to(dt)
    if need_feats:
        if kmap.identity is not None:
            grad_in = _mm(go_dt, w_dt[kmap.identity].T).to(feats.dtype)
        else:
            grad_in = feats.new_zeros((kmap.n_in, cin))
    if need_weight:
        grad_w = torch.zeros_like(weight)
        if kmap.identity is not None:
            grad_w[kmap.identity] = torch.mm(f_dt.T, go_dt)
    wt = w_dt.transpose(1, 2)
    chunks = kmap.chunks(_rows(cin, cout))
    if chunks:
        rows = max(r1 - r0 for r0, r1, _ in chunks)
        gobuf = go_dt.new_empty((rows, cout))
        fibuf = f_dt.new_empty((rows, cin)) if need_weight else None
        pbuf = go_dt.new_empty((rows, cin)) if need_feats else None
    for r0, r1, pieces in chunks:
        n = r1 - r0
        go = torch.index_select(go_dt, 0, kmap.out_idx[r0:r1], out=gobuf[:n])
        fi = torch.index_select(f_dt, 0, kmap.in_idx[r0:r1], out=fibuf[:n]) if need_weight else None
        prod = pbuf[:n] if need_feats else None
        for k, a, b in pieces:
            if need_weight:
                if dt == grad_w.dtype:
                    grad_w[k].addmm_(fi[a:b].T, go[a:b])
                else:
                    grad_w[k] += torch.mm(fi[a:b].T, go[a:b]).to(grad_w.dtype)
            if need_feats:
                _mm(go[a:b], wt[k], out=prod[a:b])
        if need_feats:
            grad_in.index_add_(0, kmap.in_idx[r0:r1], prod.to(grad_in.dtype))
    return grad_in, grad_w


class SparseConvFunction(torch.autograd.Function):
    """Autograd wrapper of the gather-GEMM-scatter convolution (first-order gradients)."""

    @staticmethod
    def forward(ctx, feats: torch.Tensor, weight: torch.Tensor, kmap: KernelMap,
                dtype: torch.dtype | None = None) -> torch.Tensor:
        feats = feats.contiguous()
        weight = weight.contiguous()
        ctx.save_for_backward(feats, weight)
        ctx.kmap, ctx.dtype = kmap, dtype
        return gemm_forward(feats, weight, kmap, dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: torch.Tensor):
        feats, weight = ctx.saved_tensors
        gi, gw = gemm_backward(feats, weight, ctx.kmap, grad_out, ctx.needs_input_grad[0],
                               ctx.needs_input_grad[1], ctx.dtype)
        return gi, gw, None, None


def conv_gemm(feats: torch.Tensor, weight: torch.Tensor, kmap: KernelMap) -> torch.Tensor:
    """The one entry point every sparse conv layer calls: differentiable; GEMMs in the `training_precision` of
    the enclosing block when gradients are needed (training; default full), else in its `gemm_precision`."""
    grads = torch.is_grad_enabled() and (feats.requires_grad or weight.requires_grad)
    return SparseConvFunction.apply(feats, weight, kmap, _GEMM_DTYPE[grads])

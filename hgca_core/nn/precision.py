"""Names of the sparse convolutions' GEMM precisions, and the default every entry point shares.

Torch-free, so that argument parsers and result records can name precisions without importing torch.

The default is fp32 because it is the precision whose result does not depend on the thread count: with MKL's
strict reproducibility mode (set when `hgca_core` is imported) every float32 GEMM gives the same bits on 1 or 2
threads. bf16 GEMMs run in oneDNN, which has no such mode: on CPUs with AMX a completion's mesh differs between
1 and 2 threads. `bf16` (and `auto`: bf16 where the hardware has it) stay available for speed, with that caveat.
"""
from __future__ import annotations

PRECISIONS = ("auto", "fp32", "bf16")
DEFAULT_PRECISION = "fp32"

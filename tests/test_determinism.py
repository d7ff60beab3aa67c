"""What the README promises about determinism, end to end: the same input, seed and weights give the same mesh
(sha256 of the file) on 1 and 2 threads, at the default precision; and what makes it hold (MKL's strict mode,
set by `import hgca_core`), checked on the GEMM that used to break it."""
from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import hgca_core

EXAMPLE = Path(hgca_core.__file__).parent / "examples"


def _env(threads: int) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("MKL_CBWR", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    env["OMP_NUM_THREADS"] = str(threads)
    return env


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


WEIGHT_GRAD = """
import hgca_core, torch
g = torch.Generator().manual_seed(0)
a, b = torch.randn(200_000, 32, generator=g), torch.randn(200_000, 32, generator=g)
torch.set_num_threads(1); one = torch.mm(a.T, b)
torch.set_num_threads(2); two = torch.mm(a.T, b)
print(torch.equal(one, two))
"""


def test_import_makes_a_row_reduction_gemm_thread_count_independent():
    """A weight gradient's GEMM reduces over every row; MKL splits that reduction by thread count unless its strict
    mode is on. With the mode forced off (a user's own MKL_CBWR wins) the same GEMM differs: the check can fail."""
    run = lambda env: subprocess.run([sys.executable, "-c", WEIGHT_GRAD], env=env, capture_output=True, text=True,
                                     check=True).stdout.strip()
    assert run(_env(2)) == "True"
    assert run({**_env(2), "MKL_CBWR": "AUTO"}) == "False"


def test_complete_gives_the_same_mesh_on_1_and_2_threads(tmp_path):
    """`hgca complete`, full stage (coarse GCA, cGCA, implicit mesh) with the shipped weights, default precision."""
    scans = [str(EXAMPLE / f"street_scan{i}.laz") for i in (0, 1)]
    shas = []
    for threads in (1, 2):
        out = tmp_path / f"t{threads}.ply"
        subprocess.run([sys.executable, "-m", "hgca_core.cli", "complete", *scans, "--poses", str(EXAMPLE / "poses.json"),
                        "--region", "30,0,1,9.6,9.6,6,0", "--t1", "10", "--t2", "5", "--progress", "none",
                        "-o", str(out)], env=_env(threads), check=True, capture_output=True, timeout=600)
        shas.append(_sha(tmp_path / f"t{threads}_s0.ply"))
    assert shas[0] == shas[1]

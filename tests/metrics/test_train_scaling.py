"""benchmarks/train_scaling.py: the three configurations run the same recipe and the same chains a step in all."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import train_scaling  # noqa: E402


def _opt(cmd: list[str], flag: str) -> str:
    return cmd[cmd.index(flag) + 1]


def _set(cmd: list[str], key: str) -> str:
    return next(v.split("=", 1)[1] for f, v in zip(cmd, cmd[1:]) if f == "--set" and v.startswith(key + "="))


def test_the_ranks_split_the_batch_and_the_wide_process_gets_the_threads(tmp_path):
    one, env1 = train_scaling.command("one", "d", tmp_path / "a", 30, 4, 2, 29600)
    wide, env2 = train_scaling.command("threads", "d", tmp_path / "b", 30, 4, 2, 29601)
    ranks, env3 = train_scaling.command("ranks", "d", tmp_path / "c", 30, 4, 2, 29602)
    assert (_set(one, "batch"), _opt(one, "--threads"), env1["OMP_NUM_THREADS"]) == ("4", "1", "1")
    assert (_set(wide, "batch"), _opt(wide, "--threads"), env2["OMP_NUM_THREADS"]) == ("4", "2", "2")
    assert (_set(ranks, "batch"), _opt(ranks, "--threads"), env3["OMP_NUM_THREADS"]) == ("2", "1", "1")
    assert _opt(ranks, "--nproc_per_node") == "2" and "torch.distributed.run" in ranks
    for cmd in (one, wide, ranks):   # one recipe, the trainer's own step count, no validation inside the timing
        tail = cmd[cmd.index("train"):]
        assert tail[0] == "train" and _opt(tail, "--max-steps") == "30" and _opt(tail, "--recipe") == "coarse-shipped"
        assert float(_set(tail, "val_every")) > 1000
    with pytest.raises(ValueError, match="does not split over 2 ranks"):
        train_scaling.command("ranks", "d", tmp_path / "d", 30, 3, 2, 29603)

"""benchmarks/train_scaling.py: the three configurations run the same recipe and the same chains a step in all. The
script is run as a subprocess (`--print-commands`, nothing trained): tests never import benchmarks/."""
import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "train_scaling.py"


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), "--data", "d", "--steps", "30", "--procs", "2",
                           "--print-commands", *args], capture_output=True, text=True, timeout=120)


def _opt(cmd: list[str], flag: str) -> str:
    return cmd[cmd.index(flag) + 1]


def _set(cmd: list[str], key: str) -> str:
    return next(v.split("=", 1)[1] for f, v in zip(cmd, cmd[1:]) if f == "--set" and v.startswith(key + "="))


def test_the_ranks_split_the_batch_and_the_wide_process_gets_the_threads(tmp_path):
    res = _run("--batch", "4", "--out", str(tmp_path / "t.json"))
    assert res.returncode == 0, res.stderr
    shown = json.loads(res.stdout)
    one, wide, ranks = (shown[k]["cmd"] for k in ("one", "threads", "ranks"))
    assert (_set(one, "batch"), _opt(one, "--threads"), shown["one"]["omp"]) == ("4", "1", "1")
    assert (_set(wide, "batch"), _opt(wide, "--threads"), shown["threads"]["omp"]) == ("4", "2", "2")
    assert (_set(ranks, "batch"), _opt(ranks, "--threads"), shown["ranks"]["omp"]) == ("2", "1", "1")
    assert _opt(ranks, "--nproc_per_node") == "2" and "torch.distributed.run" in ranks
    for cmd in (one, wide, ranks):   # one recipe, the trainer's own step count, no validation inside the timing
        tail = cmd[cmd.index("train"):]
        assert tail[0] == "train" and _opt(tail, "--max-steps") == "30" and _opt(tail, "--recipe") == "coarse-shipped"
        assert float(_set(tail, "val_every")) > 1000
    assert not (tmp_path / "t.json").exists()   # nothing ran, nothing written


def test_a_batch_the_ranks_cannot_split_is_refused(tmp_path):
    res = _run("--batch", "3", "--out", str(tmp_path / "t.json"))
    assert res.returncode == 2 and "does not split over 2 ranks" in res.stderr, res.stderr

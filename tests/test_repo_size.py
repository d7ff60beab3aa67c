"""The repository stays small enough to travel to a lent GPU machine with its training data: the device tool
copies the tracked files plus the carried ones and refuses more than 64 MiB in all, and packed training data
(`hgca synth --pack`, ~60 kB a scene) needs the rest. Large results belong in git history, not the tree."""
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BUDGET_MIB = 48   # leaves 16 MiB of the device tool's 64 for packed scenes (~270)


def test_tracked_files_leave_room_for_training_data_on_the_gpu_machine():
    try:
        out = subprocess.run(["git", "-C", str(REPO), "ls-files", "-z"], capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    files = [REPO / f for f in out.decode().split("\0") if f]
    sizes = sorted(((f.stat().st_size, f) for f in files if f.is_file()), reverse=True)
    total = sum(s for s, _ in sizes) / 2**20
    assert total <= BUDGET_MIB, (f"tracked files: {total:.1f} MiB > {BUDGET_MIB} MiB; largest: "
                                 + ", ".join(f"{f.relative_to(REPO)} ({s / 2**20:.1f} MiB)" for s, f in sizes[:5]))

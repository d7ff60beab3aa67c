"""scripts/build_train_data.sh rebuilds, on a new machine, the scenes the coarse fine-tunes trained and were selected
on. Its folders must hold the seeds the model card names (generator 6 train seeds 0-1,359 and generator 7 seeds
1,500-1,670), with no seed in two folders and none shared with val or test."""
import os
import re
import subprocess
from pathlib import Path

from hgca_core.dataset.samples import SPLITS

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "build_train_data.sh"


def dry_run(**env: str) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(SCRIPT)], env={**os.environ, "DRY_RUN": "1", "DATA": "/d", **env},
                          capture_output=True, text=True)


def planned() -> dict[str, tuple[int, set[int]]]:
    """folder -> (generator, seeds) from the script's commands."""
    out = dry_run()
    assert out.returncode == 0, out.stderr
    plan = {}
    for line in out.stdout.splitlines():
        flags = dict(re.findall(r"--(split|first|count|generator|out) (\S+)", line))
        first, count = int(flags.get("first", 0)), int(flags["count"])
        base = SPLITS[flags["split"]]
        plan[Path(flags["out"]).name] = (int(flags["generator"]), set(range(base + first, base + first + count)))
    return plan


def test_train_folders_hold_the_cards_seeds_once_each():
    plan = planned()
    gen6 = [plan[f] for f in ("s6a", "s6b", "s6c", "s6d")]
    assert all(g == 6 for g, _ in gen6)
    seeds6 = [s for _, s in gen6]
    assert set().union(*seeds6) == set(range(1360)) and sum(map(len, seeds6)) == 1360
    assert plan["s7a"] == (7, set(range(1500, 1671)))


def test_val_and_test_folders_are_what_the_selection_reads():
    plan = planned()
    assert plan["v2f"] == (6, set(range(1_000_000, 1_000_016)))      # val_cut.py's 16 scenes, the trainer's val
    assert plan["synth2cal"] == (6, set(range(1_000_016, 1_000_064)))
    assert plan["synth2f"] == (6, set(range(2_000_000, 2_000_008)))  # `hgca eval --split test --count 8`
    train = set().union(*(s for f, (_, s) in plan.items() if f.startswith("s6") or f == "s7a"))
    assert all(s < 1_000_000 for s in train)


def test_an_unknown_folder_is_refused_by_name():
    out = dry_run(FOLDERS="v2f s9z")
    assert out.returncode == 2 and "unknown folder 's9z'" in out.stderr

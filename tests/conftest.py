"""Shared fixtures: a tiny dataset on disk and the real fixture folder (see hgca_testdata for both)."""
from __future__ import annotations

import signal
from pathlib import Path

import numpy as np
import pytest

import hgca_core  # noqa: F401  (first: it sets MKL's strict reproducibility mode before torch runs any GEMM)
import torch  # noqa: E402

from hgca_testdata import require_real, tiny_sample

# A suite started in the background of a script (`cmd &`, nohup) inherits SIGINT ignored, and so would every CLI
# the tests start: `hgca` keeps an ignored SIGINT ignored (as Python does), and the tests that Ctrl-C it would
# wait in vain. A Python-level handler here is reset to the default in each child at exec.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


# The files that hold the suite's longest tests (each 20-190 s on 2 busy cores, `--durations=40`), longest first.
# Under xdist they start first, and the schedule steals work (below), so that no worker begins a long test while the
# others run out of work: the suite's wall time on 2 workers is bounded by its tail. Collected alphabetically,
# tests/training (the four 50-step recipe runs, the trainer's runs) would come last.
LONGEST_FILES = (
    "tests/training/test_recipes.py", "tests/test_eval_cli.py", "tests/drive/test_gpu_check.py",
    "tests/test_demo_cli.py", "tests/training/test_trainer.py", "tests/drive/test_drive_run.py",
    "tests/test_complete_safety.py", "tests/drive/test_drive_ray_memory.py", "tests/drive/test_drive_threads.py",
    "tests/models/test_autoencoder.py", "tests/test_eval_real.py", "tests/test_determinism.py",
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Under xdist, the files of LONGEST_FILES first (in that order, each file's tests kept together so that its
    module fixtures are made once), the others after them in their own order."""
    if not hasattr(config, "workerinput"):   # collected by each xdist worker, never by a serial run
        return
    rank = {name: i for i, name in enumerate(LONGEST_FILES)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::", 1)[0], len(rank)))


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log):
    """`-n N` schedules by work stealing unless another `--dist` is asked for. Why: xdist's default (`load`) hands
    each worker 200 consecutive tests at first, so the long tests at the front would all go to one worker; work
    stealing splits the list in halves and an idle worker takes the back half of another's queue, down to single
    tests, so the workers finish together."""
    asked = any(a in ("-d", "--dist") or a.startswith("--dist=") for a in config.invocation_params.args)
    if asked or config.getoption("distload", False) or config.getoption("dist") != "load":
        return None
    from xdist.scheduler import WorkStealingScheduling

    return WorkStealingScheduling(config, log)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("tiny_data")
    for split, seeds in (("train", range(3)), ("val", range(100, 102))):
        (root / split).mkdir()
        for s in seeds:
            np.savez(root / split / f"sample_{s:07d}.npz", **tiny_sample(s))
    return root


@pytest.fixture
def dataset(tiny_dataset, tmp_path) -> Path:
    """A private copy of the tiny dataset, for tests that write beside the samples (free-space sidecars)."""
    import shutil

    root = tmp_path / "data"
    shutil.copytree(tiny_dataset, root)
    return root


@pytest.fixture(scope="session")
def real_dir() -> Path:
    """The real-files folder tests/data/real: a skip where it is missing, a failure under CI."""
    return require_real()


@pytest.fixture(scope="session")
def small_weights(tmp_path_factory) -> Path:
    """Small untrained coarse weights (3 steps): the whole `hgca complete` path in a few seconds."""
    from hgca_core.models.gca import GCAConfig, GCAKernel
    from hgca_core.training.export import save_weights

    torch.manual_seed(0)
    cfg = GCAConfig(channels=(8, 8, 16, 16, 16), steps=3)
    path = tmp_path_factory.mktemp("w") / "coarse_small.pt"
    save_weights(path, GCAKernel(cfg), {"stage": "test"})
    return path


@pytest.fixture
def one_thread():
    """Small tensors: one torch thread beats two that wait for each other on a busy 2-core machine."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)

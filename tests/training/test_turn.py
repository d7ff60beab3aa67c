"""`--turn`: training inputs turned by a random yaw about the sensor (`data.turn_cells`), so the coarse model sees
streets in every direction, as real scans arrive, not only along the region's x axis."""

import numpy as np
import pytest

from hgca_core.cli import main
from hgca_core.models.gca import GCAConfig
from hgca_core.models.weights import load_file
from hgca_core.training.coarse import CoarseTask
from hgca_core.training.data import coarse_pair, free_cells, turn_cells

pytestmark = pytest.mark.usefixtures("one_thread")
SMALL = dict(channels=(8, 8, 16, 16, 16))


def keys(cells: np.ndarray) -> set:
    return {tuple(c) for c in np.asarray(cells).tolist()}


def test_turn_cells_quarter_turns_are_exact_and_walls_stay_walls() -> None:
    grid = (40, 30, 6)
    rng = np.random.default_rng(0)
    cells = np.unique(np.c_[rng.integers(5, 35, 300), rng.integers(5, 25, 300), rng.integers(0, 6, 300)], axis=0)
    (same,) = turn_cells([cells], grid, 0.0)
    assert keys(same) == keys(cells)
    # a quarter turn about the centre (20, 15) sends the centre of cell (x, y) to (35 - y, x - 5): exact
    (quarter,) = turn_cells([cells], grid, np.pi / 2)
    want = {(34 - y, x - 5, z) for x, y, z in cells.tolist() if 0 <= 34 - y < 40 and 0 <= x - 5 < 30}
    assert keys(quarter) == want
    # a one-cell wall along x, turned 30 deg: as many cells per layer, on the 30 deg line through the centre,
    # one connected piece (8-neighbours) per layer
    big = (100, 100, 2)
    wall = np.array([[x, 50, z] for x in range(20, 80) for z in range(2)])
    (turned,) = turn_cells([wall], big, np.radians(30))
    layer = turned[turned[:, 2] == 0]
    assert abs(len(layer) - 60) <= 3
    centre = layer[:, :2] + 0.5 - 50.0
    off_line = np.abs(centre[:, 1] * np.cos(np.radians(30)) - centre[:, 0] * np.sin(np.radians(30)))
    assert off_line.max() < 1.0 and np.ptp(layer[:, 0]) > 45
    order = layer[np.argsort(layer[:, 0] * 1000 + layer[:, 1])]
    assert np.abs(np.diff(order[:, :2], axis=0)).max() <= 1


def flipped(cells: np.ndarray, grid: tuple[int, int, int]) -> list[set]:
    """The cell set under each of the four x/y flips a training crop may draw."""
    c = np.asarray(cells)
    out = []
    for fx in (False, True):
        for fy in (False, True):
            d = c.copy()
            if fx:
                d[:, 0] = grid[0] - 1 - d[:, 0]
            if fy:
                d[:, 1] = grid[1] - 1 - d[:, 1]
            out.append(keys(d))
    return out


def test_turned_training_inputs(dataset, monkeypatch) -> None:
    """With a yaw every set of a chain (s^0, ground truth, free space) is the sample's turned by it, under one
    crop's flips; a yaw is drawn only for the share asked for; the recipe records the share."""
    cfg = GCAConfig(**SMALL, steps=3, free_space=True)
    path = sorted((dataset / "train").glob("sample_*.npz"))[0]
    turned = CoarseTask(str(dataset), cfg, crop=None, focus_share=0.0, turn_share=1.0)
    assert turned.recipe()["turn_share"] == 1.0
    s0, gt, grid = coarse_pair(path)
    yaw = 1.1
    (t_s0, t_gt), _, extra = turned.example(path, [], np.random.default_rng(3), yaw=yaw)
    w_s0, w_gt, w_free = turn_cells([s0, gt, free_cells(path)], grid, yaw)
    t_free = np.argwhere(extra["free"].numpy())
    combo = [i for i, v in enumerate(flipped(w_gt, grid)) if v == keys(t_gt.numpy())]
    assert len(combo) == 1 and flipped(w_s0, grid)[combo[0]] == keys(t_s0.numpy())
    assert flipped(w_free, grid)[combo[0]] == keys(t_free)
    assert keys(t_gt.numpy()) not in flipped(gt, grid) and len(t_gt) > 0.6 * len(gt)
    # a yaw is drawn for the share asked for, none without turns
    yaws = []
    real_example = CoarseTask.example

    def spy(self, *a, **k):  # noqa: ANN001, ANN002, ANN003, ANN202
        yaws.append(a[5] if len(a) > 5 else k.get("yaw"))   # (path, more, rng, focus, height, yaw)
        return real_example(self, *a, **k)

    monkeypatch.setattr(CoarseTask, "example", spy)
    for share in (1.0, 0.0):
        task = CoarseTask(str(dataset), cfg, crop=16, focus_share=0.5, turn_share=share)
        for k in range(4):
            task.new_example(np.random.default_rng(k))
    assert all(y is not None and 0 <= y < 2 * np.pi for y in yaws[:4]) and len(set(yaws[:4])) == 4
    assert yaws[4:] == [None] * 4


def test_train_turn_is_recorded_and_kept_on_resume(dataset, tmp_path) -> None:
    out = tmp_path / "run"
    base = ["train", "--data", str(dataset), "--out", str(out), "--set", "channels=8,8,16,16,16",
            "--set", "crop=16", "--threads", "1", "--no-progress", "--set", "val_every=1000"]
    assert main(base + ["--set", "turn=0.5", "--max-steps", "1"]) == 0
    assert main(base + ["--resume", "--max-steps", "2"]) == 0
    sessions = load_file(out / "ckpt.pt")["state"]["sessions"]
    assert [s["recipe"]["turn_share"] for s in sessions] == [0.5, 0.5]
    assert main(base[:3] + ["--out", str(tmp_path / "bad"), "--set", "turn=2", "--max-steps", "1"]) == 2

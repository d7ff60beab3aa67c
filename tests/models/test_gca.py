import pytest
import torch

from hgca_core.geometry import coords as cs
from hgca_core.models.cgca import CGCAConfig
from hgca_core.models import gca
from hgca_core.models.gca import GCAConfig, GCAKernel, sample
from hgca_core.models.infusion import alpha
from hgca_core.models.planner import rough_target
from hgca_core.nn.sparse import CellState

GRID = (24, 24, 20)


def _plane():
    xy = torch.stack(torch.meshgrid(torch.arange(4, 20), torch.arange(4, 20), indexing="ij"), -1).reshape(-1, 2)
    return cs.with_batch(torch.cat([xy, torch.full((len(xy), 1), 5)], 1))


def _model(planner=True):
    torch.manual_seed(0)
    return GCAKernel(GCAConfig(channels=(8, 8, 16, 16, 16), use_planner=planner, grid=GRID))


def test_kernel_logits_on_neighbourhood_and_planner_shapes():
    m = _model()
    s0 = _plane()
    nbhd = m.neighbourhood(CellState(s0, GRID))
    assert len(nbhd) == 18 * 18 * 3 and nbhd.grid == GRID  # the plane dilated by one cell in every direction
    bev = m.bev(CellState(s0, GRID), 1)
    assert bev.rough.shape == (1, 4, 8, 8)
    assert len(bev.spade) == m.unet.num_levels
    logits = m(nbhd, s0, s0, bev)
    assert logits.shape == (len(nbhd),) and torch.isfinite(logits).all()
    logits.sum().backward()
    assert m.planner.pointnet.inp.weight.grad is not None  # the planner is in the graph


def test_spade_finds_the_pillars_of_the_grid_the_cells_carry(monkeypatch):
    m, s0, grid = _model(), _plane(), (30, 24, 20)           # 10 x 8 pillars of 3 cells
    hws, real = [], gca.pillar_index
    monkeypatch.setattr(gca, "pillar_index", lambda c, s, hw: hws.append(hw) or real(c, s, hw))
    with torch.no_grad():
        bev = m.bev(CellState(s0, grid), 1)
        m(m.neighbourhood(CellState(s0, grid)), s0, s0, bev)
    assert bev.rough.shape == (1, 4, 10, 8) and len(hws) == len(bev.spade) and set(hws) == {(10, 8)}


def test_rough_target_marks_height_bins():
    gt = torch.tensor([[0, 0, 0, 0], [0, 5, 5, 19], [0, 23, 23, 10]])
    t = rough_target(gt, 1, GRID, 4)
    assert t.shape == (1, 4, 8, 8)
    assert t[0, 0, 0, 0] == 1 and t[0, 3, 1, 1] == 1 and t[0, 2, 7, 7] == 1 and t.sum() == 3


def test_alpha_schedule_is_shared_and_clipped():
    for cfg in (GCAConfig(), CGCAConfig()):         # both stages train with the paper's 0.15 + 0.005 t
        assert alpha(cfg, 0) == 0.15 and abs(alpha(cfg, 10) - 0.2) < 1e-12 and alpha(cfg, 1000) == 1.0
    assert alpha(GCAConfig(alpha0=-0.5, alpha1=0.1), 2) == 0.0 and alpha(GCAConfig(alpha0=-0.5, alpha1=0.1), 6) > 0


def test_sampling_is_seeded_and_grows_within_reach():
    m = _model(planner=False)
    s0 = _plane()
    a = sample(m, CellState(s0, GRID), 3, torch.Generator().manual_seed(1))
    b = sample(m, CellState(s0, GRID), 3, torch.Generator().manual_seed(1))
    assert torch.equal(a, b)
    c = sample(m, CellState(s0, GRID), 3, torch.Generator().manual_seed(2))
    # the chain is alive (a dead chain returns an empty set and fails here) and the seed matters
    assert len(a) > len(s0) and len(c) > len(s0) and not torch.equal(a, c)
    reach = cs.dilate(s0, 3, bounds=GRID)           # one Chebyshev cell per step, never outside the grid
    for x in (a, c):
        assert torch.equal(x, cs.unique(x)) and bool(cs.isin(x, reach).all()) and bool((x[:, 0] == 0).all())


def test_a_dead_chain_stops():
    m = _model(planner=False)
    m.forward = lambda nbhd, *args: torch.full((len(nbhd),), -50.0)     # every cell empties
    steps = []
    out = sample(m, CellState(_plane(), GRID), 5, torch.Generator().manual_seed(0), lambda t, n: steps.append(t))
    assert len(out) == 0 and steps == [0, 1]        # the planner event, one step, then no more work


def test_a_higher_last_step_threshold_keeps_a_subset_of_the_same_chain():
    m = _model(planner=False)
    s0 = _plane()
    base = sample(m, CellState(s0, GRID), 3, torch.Generator().manual_seed(1))
    probs = []
    forward = m.forward
    m.forward = lambda *a: probs.append(torch.sigmoid(forward(*a))) or forward(*a)
    m.cfg.keep = 0.6
    sure = sample(m, CellState(s0, GRID), 3, torch.Generator().manual_seed(1))
    # the same draws before the last step; there, only the cells with p > 0.6 stay of those with p > 0.5
    last = probs[-1]
    assert int((last > 0.6).sum()) == len(sure) < int((last > 0.5).sum()) == len(base)
    assert bool(cs.isin(sure, base).all())


def test_the_threshold_must_lie_inside_zero_one():
    for bad in (0.0, 1.0, 1.5, -0.1):
        with pytest.raises(ValueError, match="keep must lie strictly between 0 and 1"):
            GCAKernel(GCAConfig(channels=(8, 8, 16, 16, 16), grid=GRID, keep=bad))


def test_a_negative_logit_shift_draws_a_subset_at_every_step_and_shifts_the_last_threshold():
    """bias is added to every step's logits: with the draws of the same seed a step keeps a subset of the cells it
    keeps without it (checked on the first step, where both chains see the same neighbourhood), and the last step
    keeps p > keep of the shifted probabilities."""
    m = _model(planner=False)
    s0 = _plane()
    one = sample(m, CellState(s0, GRID), 2, torch.Generator().manual_seed(1))
    logits = []
    forward = m.forward
    m.forward = lambda *a: logits.append(forward(*a)) or logits[-1]
    m.cfg.bias = -0.7
    first = sample(m, CellState(s0, GRID), 1, torch.Generator().manual_seed(1))   # one step: the last, thresholded
    assert len(first) == int((torch.sigmoid(logits[-1] - 0.7) > 0.5).sum())
    m.cfg.bias = 0.0
    draws_free = sample(m, CellState(s0, GRID), 2, torch.Generator().manual_seed(1))
    assert torch.equal(draws_free, one)                                # a shift of 0 is the paper's chain
    m.cfg.bias = -0.7
    less = sample(m, CellState(s0, GRID), 2, torch.Generator().manual_seed(1))
    m.cfg.bias = 0.0
    # step one of both chains: same neighbourhood and draws, so u < sigmoid(l - 0.7) implies u < sigmoid(l)
    u = torch.rand(len(m.neighbourhood(CellState(s0, GRID))), generator=torch.Generator().manual_seed(1))
    hood = m.neighbourhood(CellState(s0, GRID))
    l0, nb = forward(hood, s0, s0, None, None), hood.coords
    kept_shifted, kept = nb[u < torch.sigmoid(l0 - 0.7)], nb[u < torch.sigmoid(l0)]
    assert 0 < len(kept_shifted) < len(kept) and bool(cs.isin(kept_shifted, kept).all())
    assert len(less) < len(one)
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match="bias must be a finite number"):
            GCAKernel(GCAConfig(channels=(8, 8, 16, 16, 16), grid=GRID, bias=bad))

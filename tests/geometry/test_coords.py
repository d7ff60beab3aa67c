import torch

from hgca_core.geometry import coords as cs


def _set(rows):
    return cs.unique(torch.tensor(rows, dtype=torch.long))


def test_pack_unpack_roundtrip_and_order():
    c = torch.tensor([[0, -5, 3, 100], [1, 0, 0, 0], [0, -5, 3, 99], [3, 131071, -131072, 7]])
    assert torch.equal(cs.unpack(cs.pack(c)), c)
    keys = cs.pack(c)
    order = torch.argsort(keys)
    rows = c[order].tolist()
    assert rows == sorted(rows)


def test_dilate_radius_metrics_and_bounds():
    one = _set([[0, 5, 5, 5]])
    assert len(cs.dilate(one, 1)) == 27
    assert len(cs.dilate(one, 2)) == 125
    assert len(cs.dilate(one, 1, metric="l1")) == 7
    assert len(cs.dilate(one, 2, metric="l2")) == 33
    corner = _set([[0, 0, 0, 0]])
    grown = cs.dilate(corner, 1, bounds=(10, 10, 10))
    assert len(grown) == 8 and grown[:, 1:].min() == 0
    two = _set([[0, 0, 0, 0], [1, 0, 0, 0]])  # batches never leak into each other
    assert len(cs.dilate(two, 1)) == 54


def test_union_isin_lookup():
    a, b = _set([[0, 1, 1, 1], [0, 2, 2, 2]]), _set([[0, 2, 2, 2], [1, 2, 2, 2]])
    u = cs.union(a, b)
    assert len(u) == 3
    assert cs.isin(a, b).tolist() == [False, True]
    keys = cs.pack(u)
    assert cs.lookup(torch.tensor([[1, 2, 2, 2], [0, 9, 9, 9]]), keys).tolist() == [2, -1]


def test_upsample_then_downsample_is_identity():
    a = _set([[0, 1, -1, 3], [0, 4, 4, 4], [1, 0, 0, 0]])
    up = cs.upsample2(a)
    assert len(up) == 24
    assert torch.equal(cs.downsample2(up), a)
    # negative coordinates floor correctly: child -1 belongs to parent -1, not 0
    assert cs.downsample2(_set([[0, -1, 0, 0]])).tolist() == [[0, -1, 0, 0]]

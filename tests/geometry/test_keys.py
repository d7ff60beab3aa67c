"""The one cell-key packer: numpy and torch, batched and not, negative coordinates, order, linearity."""
import numpy as np
import pytest
import torch

from hgca_core.errors import InputError
from hgca_core.geometry import keys


def test_numpy_roundtrip_with_negative_coordinates_and_lexicographic_order():
    c = np.array([[-5, 3, 0], [131071, -131072, 7], [0, 0, 0], [-1, -1, -1], [-131072, 131071, -131072]])
    k = keys.pack(c)
    assert k.dtype == np.int64
    assert np.array_equal(keys.unpack(k, batched=False), c)
    assert np.array_equal(c[np.argsort(k)], c[np.lexsort(c[:, ::-1].T)])


def test_torch_and_numpy_give_the_same_keys_and_batch_zero_is_unbatched():
    c = np.array([[-5, 3, 0], [17, -9, 2], [0, 0, 0]])
    t = torch.from_numpy(c)
    assert torch.equal(keys.pack(t), torch.from_numpy(keys.pack(c)))
    b0 = torch.cat([torch.zeros(3, 1, dtype=torch.long), t], 1)
    assert torch.equal(keys.pack(b0), keys.pack(t))          # an unbatched row is the same cell in batch 0
    b = torch.tensor([[2, -7, 0, 5], [0, 1, 2, 3], [1, -131072, 131071, -1]])
    assert torch.equal(keys.unpack(keys.pack(b), batched=True), b)
    assert torch.argsort(keys.pack(b)).tolist() == [1, 2, 0]  # the batch comes first in the order


def test_delta_is_the_key_of_an_offset():
    rng = np.random.default_rng(0)
    c = rng.integers(-1000, 1000, (200, 3))
    d = rng.integers(-3, 4, (200, 3))
    assert np.array_equal(keys.pack(c + d), keys.pack(c) + keys.delta(d))


def test_unique_rows_and_range_check():
    c = np.array([[3, -2, 1], [3, -2, 1], [-4, 0, 0]])
    assert keys.unique_rows(c).tolist() == [[-4, 0, 0], [3, -2, 1]]
    assert keys.unique_rows(np.zeros((0, 3))).shape == (0, 3)
    with pytest.raises(InputError, match="outside"):
        keys.unique_rows(np.array([[keys.OFFSET, 0, 0]]))
    with pytest.raises(InputError, match="outside"):
        keys.unique_rows(np.array([[0, 0, -keys.OFFSET - 1]]))
    keys.check_range(np.array([[-keys.OFFSET, keys.OFFSET - 1, 0]]))   # the extremes are fine

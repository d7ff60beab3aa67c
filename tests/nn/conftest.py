"""tests/nn runs its tiny problems on one intra-op thread: on a shared 2-core machine, OpenMP barriers
between two threads cost more than these ops do (the determinism test sets its own thread counts)."""
from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch


@pytest.fixture(autouse=True)
def _one_thread() -> Iterator[None]:
    prev = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(prev)

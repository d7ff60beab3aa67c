"""A LAS/LAZ header that counts fewer points than the file stores is refused with both numbers: laspy reads
what the header counts, so the rest were dropped without a word (1500 of 2000 read)."""
from __future__ import annotations

import struct

import laspy
import numpy as np
import pytest

from hgca_core.errors import InputError
from hgca_core.io import read_scan


def laz_of(path, n: int) -> bytes:
    pts = np.random.default_rng(0).uniform([0, 0, 0], [80, 80, 10], (n, 3)) + [500_000.0, 5_000_000.0, 100.0]
    las = laspy.LasData(laspy.LasHeader(point_format=3, version="1.2"))
    las.header.offsets, las.header.scales = np.floor(pts.min(0)), [0.001] * 3
    las.x, las.y, las.z = pts.T
    las.intensity = np.arange(n, dtype=np.uint16)
    las.write(str(path))
    return path.read_bytes()


@pytest.mark.parametrize("declared, says", [(110_000, "holds 120000"), (100_001, "holds 120000"),
                                            (60_000, r"holds 3 chunks \(100000 points in the first 2 alone\)")])
def test_laz_of_several_chunks_with_a_low_count(tmp_path, declared, says):
    raw = bytearray(laz_of(tmp_path / "src.laz", 120_000))     # three chunks of up to 50,000 points
    assert len(read_scan(tmp_path / "src.laz")) == 120_000
    struct.pack_into("<I", raw, 107, declared)
    (tmp_path / "low.laz").write_bytes(bytes(raw))
    with pytest.raises(InputError, match=f"header says {declared} points but its compressed data {says}"):
        read_scan(tmp_path / "low.laz")


def test_copc_with_a_low_count(real_dir, tmp_path):
    """COPC chunks carry their own point counts: their sum is the file's."""
    raw = bytearray((real_dir / "simple.copc.laz").read_bytes())
    struct.pack_into("<I", raw, 107, 1000)
    struct.pack_into("<Q", raw, 247, 1000)
    (tmp_path / "low.copc.laz").write_bytes(bytes(raw))
    with pytest.raises(InputError, match="header says 1000 points but its compressed data holds 1065"):
        read_scan(tmp_path / "low.copc.laz")

"""PCD reader on files written here in all three DATA modes, plus the LZF decoder on its own."""
from __future__ import annotations

import numpy as np
import pytest

from hgca_core.errors import InputError
from hgca_core.io import read_scan
from hgca_core.io.lzf import LZFError, lzf_decompress
from hgca_testdata import refusal


def lzf_compress(data: bytes) -> bytes:
    """Greedy liblzf-compatible encoder (3-byte hash of positions, overlapping matches allowed)."""
    out, lit, table = bytearray(), bytearray(), {}
    i, n = 0, len(data)

    def flush() -> None:
        while lit:
            chunk = lit[:32]
            out.append(len(chunk) - 1)
            out.extend(chunk)
            del lit[:32]

    while i < n:
        if i + 3 <= n:
            key = data[i : i + 3]
            ref = table.get(key)
            table[key] = i
            if ref is not None and i - ref - 1 < 8192:
                length, limit = 3, min(264, n - i)
                while length < limit and data[ref + length] == data[i + length]:
                    length += 1
                flush()
                off, code = i - ref - 1, length - 2
                if code < 7:
                    out.append((code << 5) | (off >> 8))
                else:
                    out.append((7 << 5) | (off >> 8))
                    out.append(code - 7)
                out.append(off & 0xFF)
                i += length
                continue
        lit.append(data[i])
        i += 1
    flush()
    return bytes(out)


def literal_only(data: bytes) -> bytes:
    """The simplest valid LZF stream: literal runs of at most 32 bytes."""
    out = bytearray()
    for k in range(0, len(data), 32):
        chunk = data[k : k + 32]
        out.append(len(chunk) - 1)
        out.extend(chunk)
    return bytes(out)


@pytest.mark.parametrize("encode", [lzf_compress, literal_only])
def test_lzf_round_trip(encode):
    rng = np.random.default_rng(0)
    data = (b"\x00" * 1000 + rng.integers(0, 4, 3000, dtype=np.uint8).tobytes() + b"abcabcabc" * 100
            + rng.bytes(500))
    packed = encode(data)
    assert lzf_decompress(packed, len(data)) == data
    if encode is lzf_compress:
        assert len(packed) < len(data) // 2  # back references were really used


def test_lzf_overlapping_reference_by_hand():
    # literal "ab", then a back reference of length 7 at distance 2 -> "ababababa"
    stream = bytes([1]) + b"ab" + bytes([(5 << 5) | 0, 1])
    assert lzf_decompress(stream, 9) == b"ababababa"


@pytest.mark.parametrize("stream, size", [
    (bytes([5]) + b"ab", 6),               # literal run past the end
    (bytes([(1 << 5) | 0, 10]), 3),        # reference before the start of output
    (bytes([0]) + b"a", 2),                # decompresses short
    (bytes([2]) + b"abc", 2),              # decompresses long
])
def test_lzf_rejects_corrupt(stream, size):
    with pytest.raises(LZFError):
        lzf_decompress(stream, size)


FIELDS = [("x", "<f4", 1), ("y", "<f4", 1), ("z", "<f4", 1), ("intensity", "<f4", 1), ("ring", "<u2", 1),
          ("label", "<i4", 1), ("_", "u1", 2), ("normal", "<f8", 3), ("rgb", "<f4", 1)]
TYPE_CODE = {"f": "F", "u": "U", "i": "I"}


def make_cloud(n: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    dtype = np.dtype([(f"f{k}", t, (c,)) if c > 1 else (f"f{k}", t) for k, (_, t, c) in enumerate(FIELDS)])
    a = np.zeros(n, dtype=dtype)
    for k in range(3):
        a[f"f{k}"] = rng.uniform(-50, 50, n).astype(np.float32)
    a["f3"] = rng.uniform(0, 1, n).astype(np.float32)
    a["f4"] = rng.integers(0, 64, n)
    a["f5"] = rng.integers(-5, 5, n)
    a["f7"] = rng.normal(size=(n, 3))
    a["f8"] = (np.array([0x00FF8040] * n, dtype=np.uint32)).view(np.float32)
    return a


def header(n: int, mode: str, viewpoint: str | None = None, width: int | None = None) -> bytes:
    lines = [
        "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION 0.7",
        "FIELDS " + " ".join(f[0] for f in FIELDS),
        "SIZE " + " ".join(str(np.dtype(f[1]).itemsize) for f in FIELDS),
        "TYPE " + " ".join(TYPE_CODE[np.dtype(f[1]).kind] for f in FIELDS),
        "COUNT " + " ".join(str(f[2]) for f in FIELDS),
        f"WIDTH {width or n}",
        f"HEIGHT {n // (width or n) if n else 1}",
    ]
    if viewpoint:
        lines.append(f"VIEWPOINT {viewpoint}")
    lines += [f"POINTS {n}", f"DATA {mode}"]
    return ("\n".join(lines) + "\n").encode()


def encode(a: np.ndarray, mode: str, compressor=lzf_compress) -> bytes:
    if mode == "binary":
        return a.tobytes()
    if mode == "binary_compressed":
        columns = b"".join(np.ascontiguousarray(a[name]).tobytes() for name in a.dtype.names)
        packed = compressor(columns)
        return np.array([len(packed), len(columns)], dtype="<u4").tobytes() + packed
    rows = []
    for rec in a:
        values = []
        for name in a.dtype.names:
            v = rec[name]
            if name == "f8":
                values.append(repr(float(v)))  # packed rgb, full precision
            else:
                values += [repr(float(x)) if np.issubdtype(type(x), np.floating) else str(int(x))
                           for x in np.atleast_1d(v)]
        rows.append(" ".join(values))
    return ("\n".join(rows) + "\n").encode()


def check(scan, a: np.ndarray) -> None:
    np.testing.assert_array_equal(scan.points, np.column_stack([a["f0"], a["f1"], a["f2"]]).astype(np.float64))
    np.testing.assert_array_equal(scan.attributes["intensity"], a["f3"])
    np.testing.assert_array_equal(scan.attributes["ring"], a["f4"])
    np.testing.assert_array_equal(scan.attributes["label"], a["f5"])
    for k in range(3):
        np.testing.assert_array_equal(scan.attributes[f"normal_{k}"], a["f7"][:, k])
    assert (scan.attributes["red"] == 0xFF).all() and (scan.attributes["green"] == 0x80).all()
    assert (scan.attributes["blue"] == 0x40).all()
    assert "_" not in scan.attributes and "rgb" not in scan.attributes
    assert scan.attributes["ring"].dtype == np.uint16 and scan.attributes["label"].dtype == np.int32


@pytest.mark.parametrize("mode", ["ascii", "binary", "binary_compressed"])
def test_pcd_modes_read_back_identical(tmp_path, mode):
    a = make_cloud(400)
    path = tmp_path / f"cloud_{mode}.pcd"
    path.write_bytes(header(len(a), mode) + encode(a, mode))
    scan = read_scan(path)
    check(scan, a)
    assert scan.origins is None  # default viewpoint says nothing about the sensor


def test_pcd_binary_compressed_literal_stream(tmp_path):
    a = make_cloud(50, seed=3)
    path = tmp_path / "literal.pcd"
    path.write_bytes(header(len(a), "binary_compressed") + encode(a, "binary_compressed", literal_only))
    check(read_scan(path), a)


def test_pcd_organized_with_no_return_rows_and_viewpoint(tmp_path):
    a = make_cloud(60, seed=4)
    for k in range(3):
        a[f"f{k}"][::3] = np.nan  # organized cloud: every third pixel had no return
    path = tmp_path / "organized.pcd"
    path.write_bytes(header(len(a), "binary_compressed", viewpoint="1 2 3 1 0 0 0", width=20)
                     + encode(a, "binary_compressed"))
    scan = read_scan(path)
    keep = np.ones(60, bool)
    keep[::3] = False
    check(scan, a[keep])
    np.testing.assert_array_equal(scan.origins, [[1.0, 2.0, 3.0]])


def test_pcd_minimal_header_without_count(tmp_path):
    path = tmp_path / "min.pcd"
    path.write_text("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nHEIGHT 1\nDATA ascii\n1 2 3\n4 5 6\n")
    scan = read_scan(path)
    np.testing.assert_array_equal(scan.points, [[1, 2, 3], [4, 5, 6]])
    assert scan.attributes == {}


@pytest.mark.parametrize("mode", ["ascii", "binary", "binary_compressed"])
def test_pcd_truncated(tmp_path, mode):
    a = make_cloud(100)
    data = encode(a, mode)
    path = tmp_path / f"trunc_{mode}.pcd"
    path.write_bytes(header(len(a), mode) + data[: len(data) // 2])
    with pytest.raises(InputError, match=path.name):
        read_scan(path)


def test_pcd_corrupt_compressed_stream(tmp_path):
    a = make_cloud(100)
    data = bytearray(encode(a, "binary_compressed"))
    data[8:40] = bytes([0xFF]) * 32  # back references far before the start of output
    path = tmp_path / "corrupt.pcd"
    path.write_bytes(header(len(a), "binary_compressed") + bytes(data))
    refusal(read_scan, path, "corrupt binary_compressed")


@pytest.mark.parametrize("text, problem", [
    ("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nHEIGHT 1\n", "no DATA line"),
    ("FIELDS x y\nSIZE 4 4\nTYPE F F\nWIDTH 1\nHEIGHT 1\nDATA ascii\n1 2\n", "no field 'z'"),
    ("FIELDS x y z\nSIZE 4 4\nTYPE F F F\nWIDTH 1\nHEIGHT 1\nDATA ascii\n1 2 3\n", "different lengths"),
    ("FIELDS x y z\nSIZE 4 4 3\nTYPE F F F\nWIDTH 1\nHEIGHT 1\nDATA ascii\n1 2 3\n", "unsupported TYPE"),
    ("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nHEIGHT 1\nDATA zip\n1 2 3\n", "not ascii, binary"),
    ("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 0\nHEIGHT 1\nDATA ascii\n", "no points"),
])
def test_pcd_bad_headers(tmp_path, text, problem):
    path = tmp_path / "bad.pcd"
    path.write_text(text)
    refusal(read_scan, path, problem)


@pytest.mark.parametrize("kw", [{"write_ascii": True}, {}, {"compressed": True}])
def test_pcd_written_by_open3d(tmp_path, kw):
    """Files from another writer (Open3D, PCL-compatible LZF) read back exactly."""
    o3d = pytest.importorskip("open3d", reason="open3d-cpu not installed (optional 'eval' extra)")
    grid = np.stack(np.meshgrid(np.arange(60), np.arange(40), [1.5], indexing="ij"), -1).reshape(-1, 3) * 0.1
    grid = grid.astype(np.float32)
    intensity = (np.arange(len(grid)) % 7 / 7).astype(np.float32)
    pc = o3d.t.geometry.PointCloud(o3d.core.Tensor(grid))
    pc.point.intensity = o3d.core.Tensor(intensity[:, None])
    path = tmp_path / "o3d.pcd"
    assert o3d.t.io.write_point_cloud(str(path), pc, **kw)
    scan = read_scan(path)
    np.testing.assert_array_equal(scan.points, grid.astype(np.float64))
    np.testing.assert_array_equal(scan.attributes["intensity"], intensity)


@pytest.mark.parametrize("mode, change, field", [
    ("ascii", "extra rows", "POINTS"),
    ("binary", "extra rows", "POINTS"),
    ("binary_compressed", "trailing garbage", "POINTS"),
    ("binary", "trailing garbage", "POINTS"),
    ("ascii", "trailing garbage", "malformed"),
    ("binary", "width x height", "WIDTH x HEIGHT"),
    ("ascii", "fewer points", "WIDTH x HEIGHT"),
])
def test_pcd_header_that_disagrees_with_the_data_is_refused(tmp_path, mode, change, field):
    """POINTS vs the rows, WIDTH x HEIGHT vs POINTS, bytes after the data: refused naming the header field,
    where before the extra points were silently dropped or the garbage ignored (issue 11, item 5)."""
    a = make_cloud(40, seed=7)
    head = header(len(a), mode)
    data = encode(a, mode)
    if change == "extra rows":  # 50 points of data under a header that says 40
        data = encode(make_cloud(50, seed=7), mode)
    elif change == "trailing garbage":
        data += b"\x00garbage after the last point\n" if mode != "ascii" else b"1 2 3 junk\n"
    elif change == "width x height":
        head = head.replace(b"WIDTH 40", b"WIDTH 39")
    else:  # POINTS smaller than WIDTH x HEIGHT: the reader used to take POINTS and drop the rest
        head = head.replace(b"POINTS 40", b"POINTS 30")
    path = tmp_path / f"disagree_{mode}.pcd"
    path.write_bytes(head + data)
    refusal(read_scan, path, field)


def test_pcd_single_trailing_newline_after_binary_data_is_fine(tmp_path):
    a = make_cloud(30, seed=8)
    path = tmp_path / "newline.pcd"
    path.write_bytes(header(len(a), "binary") + encode(a, "binary") + b"\n")
    check(read_scan(path), a)


def test_pcd_after_a_byte_order_mark(tmp_path):
    """A UTF-8 BOM before a header that starts with FIELDS (Windows editors add one) hid that line."""
    a = make_cloud(50)
    lines = header(len(a), "ascii").decode().splitlines()
    head = ("\n".join([lines[2], *lines[:2], *lines[3:]]) + "\n").encode()
    path = tmp_path / "bom.pcd"
    path.write_bytes(b"\xef\xbb\xbf" + head + encode(a, "ascii"))
    check(read_scan(path), a)

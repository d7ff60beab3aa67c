"""LZF decompression (liblzf format), needed for PCD `binary_compressed` without an extra dependency.

Works token by token with slice copies, so cost scales with the number of tokens, not bytes.
"""
from __future__ import annotations


class LZFError(ValueError):
    """The stream is corrupt or does not decompress to the expected size."""


def lzf_decompress(data: bytes, expected_size: int) -> bytes:
    """Decompress `data`, which must expand to exactly `expected_size` bytes."""
    src = memoryview(bytes(data))
    n_in = len(src)
    out = bytearray()
    ip = 0
    while ip < n_in:
        ctrl = src[ip]
        ip += 1
        if ctrl < 32:  # literal run of ctrl + 1 bytes
            length = ctrl + 1
            if ip + length > n_in:
                raise LZFError("literal run past end of input")
            out += src[ip : ip + length]
            ip += length
        else:  # back reference
            length = ctrl >> 5
            if length == 7:
                if ip >= n_in:
                    raise LZFError("back reference length past end of input")
                length += src[ip]
                ip += 1
            if ip >= n_in:
                raise LZFError("back reference offset past end of input")
            distance = ((ctrl & 0x1F) << 8) + src[ip] + 1
            ip += 1
            length += 2
            start = len(out) - distance
            if start < 0:
                raise LZFError("back reference before start of output")
            if distance >= length:
                out += out[start : start + length]
            else:  # overlapping copy repeats the last `distance` bytes
                pattern = bytes(out[start:])
                reps, rest = divmod(length, distance)
                out += pattern * reps + pattern[:rest]
        if len(out) > expected_size:
            raise LZFError(f"output exceeds the expected {expected_size} bytes")
    if len(out) != expected_size:
        raise LZFError(f"decompressed to {len(out)} bytes, expected {expected_size}")
    return bytes(out)

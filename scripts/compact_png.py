"""Rewrite committed renderings as 256-colour palette PNGs, in place (run by hand before committing results):
`python scripts/compact_png.py benchmarks/results/real_scans_*.png`.

Why: renderings are most of a results page's bytes, and every clone carries them. A shaded mesh rendering has few
distinct colours, so a palette (fast octree, no dithering) looks the same and is 3-4x smaller. Files already in palette or grey mode,
or that would not shrink, are left as they are.
"""
from __future__ import annotations

import argparse
import io
import sys
from pathlib import Path

from PIL import Image


def compact(path: Path) -> tuple[int, int]:
    """(bytes before, bytes after) of rewriting `path` as a palette PNG; after == before where it was kept."""
    before = path.stat().st_size
    with Image.open(path) as im:
        if im.format != "PNG" or im.mode in ("P", "L", "1"):
            return before, before
        rgba = im.convert("RGBA")
    alpha = rgba.getchannel("A").getextrema() != (255, 255)
    pal = (rgba if alpha else rgba.convert("RGB")).quantize(colors=256, method=Image.Quantize.FASTOCTREE,
                                                             dither=Image.Dither.NONE)
    buf = io.BytesIO()
    pal.save(buf, format="PNG", optimize=True)
    if buf.tell() >= before:
        return before, before
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(buf.getvalue())
    tmp.replace(path)   # a crash leaves the original or the new file, never half of one
    return before, buf.tell()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("png", nargs="+", type=Path)
    args = p.parse_args(argv)
    total = [0, 0]
    for f in args.png:
        if not f.is_file():
            print(f"{f}: no such file", file=sys.stderr)
            return 2
        b, a = compact(f)
        total[0] += b
        total[1] += a
        print(f"{f}: {b:,} -> {a:,} bytes")
    print(f"all: {total[0]:,} -> {total[1]:,} bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main())

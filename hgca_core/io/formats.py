"""Which reader a file needs: by extension (with an explicit override), cross-checked against magic bytes.

The magic check turns "a LAS file renamed .ply" into a clear message instead of a parser traceback.
"""
from __future__ import annotations

import os

from hgca_core.errors import InputError

FORMATS = ("ply", "las", "pcd", "xyz", "npy", "npz", "kitti", "nuscenes", "av2")

# Longest suffix first: ".pcd.bin" must win over ".bin".
EXTENSIONS: tuple[tuple[str, str], ...] = (
    (".pcd.bin", "nuscenes"),
    (".copc.laz", "las"),
    (".ply", "ply"),
    (".las", "las"),
    (".laz", "las"),
    (".pcd", "pcd"),
    (".xyz", "xyz"),
    (".csv", "xyz"),
    (".txt", "xyz"),
    (".npy", "npy"),
    (".npz", "npz"),
    (".bin", "kitti"),
    (".feather", "av2"),
)

_LABELS = {
    "ply": "PLY", "las": "LAS/LAZ", "pcd": "PCD", "xyz": "XYZ/CSV text", "npy": "NumPy .npy",
    "npz": "NumPy .npz", "kitti": "KITTI .bin", "nuscenes": "nuScenes .pcd.bin",
    "av2": "Argoverse 2 .feather",
}


def label(fmt: str) -> str:
    """Human name of a format for messages."""
    return _LABELS.get(fmt, fmt)


def format_from_extension(path: str) -> str | None:
    """The format named by the file's extension (case-insensitive), or None when it names none."""
    name = os.path.basename(path).lower()
    for suffix, fmt in EXTENSIONS:
        if name.endswith(suffix):
            return fmt
    return None


def sniff(head: bytes) -> str | None:
    """The format the first bytes prove, or None when they prove nothing (text, raw float dumps)."""
    if head.startswith(b"ply\n") or head.startswith(b"ply\r\n"):
        return "ply"
    if head.startswith(b"LASF"):
        return "las"
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    if head.startswith(b"ARROW1"):
        return "av2"
    if head.startswith(b"PK\x03\x04") or head.startswith(b"PK\x05\x06"):
        return "npz"
    text = head.lstrip()
    if text.startswith(b"# .PCD") or text.startswith(b"VERSION") or text.startswith(b"FIELDS"):
        return "pcd"
    return None


def resolve_format(path: str, fmt: str | None = None) -> str:
    """Pick the reader for `path`, raising `InputError` for unknown names or content that contradicts them."""
    with open(path, "rb") as f:
        head = f.read(64)
    found = sniff(head)
    if fmt is not None:
        chosen = fmt.lower().strip().lstrip(".")
        if chosen in ("laz", "copc"):
            chosen = "las"
        if chosen in ("csv", "txt"):
            chosen = "xyz"
        if chosen == "bin":
            chosen = "kitti"
        if chosen not in FORMATS:
            raise InputError(f"unknown format {fmt!r}; known formats: {', '.join(FORMATS)}", path)
        source = f"--format {chosen}"
    else:
        chosen = format_from_extension(path)
        if chosen is None:
            hint = f" (its content looks like {label(found)}: pass --format {found})" if found else ""
            known = ", ".join(sorted({s for s, _ in EXTENSIONS}))
            ext = os.path.splitext(path)[1] or "(none)"
            raise InputError(f"unknown file extension {ext!r}{hint}; known extensions: {known} "
                             f"(or pass --format with one of {', '.join(FORMATS)})", path)
        source = "its extension"
    if found is not None and found != chosen:
        raise InputError(
            f"content is {label(found)} but {source} says {label(chosen)}; "
            f"rename the file or pass --format {found}",
            path,
        )
    return chosen

"""`hgca poses SEQUENCE -o poses.json [--frames A:B]`: a sequence folder's poses in our JSON, so the scan
files of a KITTI sequence, an Argoverse 2 log or nuScenes sweeps can be read by every tool (and the add-on)
with `--poses`, exactly as the folder itself places them.

`hgca poses --estimate INPUTS -o poses.json`: poses estimated from the scans themselves (KISS-ICP odometry,
`hgca_core.io.odometry`) for recordings without any: a sequence folder (its own poses ignored), a folder of scan
files, a quoted glob, scan files, or a ROS bag / E57. The JSON is the usual one plus an "estimated" record."""
from __future__ import annotations

import argparse
import glob
import json
import os
from collections.abc import Sequence as SequenceABC

from hgca_core.commands.arguments import add_format_argument, add_frames_argument, add_out_argument, \
    add_progress_argument
from hgca_core.errors import InputError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("sequence", nargs="+", metavar="INPUT",
                   help="sequence folder (KITTI velodyne/ + poses.txt + calib.txt, Argoverse 2 log, nuScenes "
                        "*.pcd.bin with poses.json); with --estimate also a folder of scan files, a quoted glob "
                        "('sweeps/*.pcd'), scan files, or a ROS bag / E57")
    p.add_argument("--estimate", action="store_true",
                   help="estimate the poses from the scans (LiDAR odometry, KISS-ICP; needs the recordings extra): "
                        "a folder's own poses are ignored; a frame the odometry cannot place is an error naming it")
    add_frames_argument(p, "frames to write (default: all)")
    add_format_argument(p)
    add_out_argument(p, "FILE.json", required=True, help="output JSON (docs/CONTRACTS.md)")
    add_progress_argument(p)


def run(args: argparse.Namespace) -> int:
    from hgca_core.io.atomic import atomic_write
    from hgca_core.io.paths import check_outputs
    from hgca_core.io.sequence import open_sequence, poses_document

    if os.path.splitext(args.out)[1].lower() != ".json":
        raise InputError("output must end in .json", args.out)
    if args.estimate:
        return _estimate(args)
    if len(args.sequence) != 1:
        raise InputError(f"give one sequence folder, not {len(args.sequence)} inputs (scan files without poses "
                         "need --estimate)", args.sequence[1])
    if args.fmt is not None:
        raise InputError("--format applies to scan files with --estimate", args.sequence[0])
    check_outputs([args.out], [args.sequence[0]])     # the folder's own poses.json is an input it reads
    out_dir = os.path.dirname(os.path.abspath(args.out))
    doc = poses_document(open_sequence(args.sequence[0], topic=args.topic), args.frames, out_dir)
    text = json.dumps(doc, indent=1).encode("utf-8")
    atomic_write(args.out, lambda f: f.write(text))
    print(f"{args.out}: poses of {len(doc['scans'])} {doc['layout']} scan(s)")
    return 0


def _estimate(args: argparse.Namespace) -> int:
    from hgca_core.progress import Progress

    progress = Progress(args.progress)
    with progress.failures_reported():
        doc = _estimate_document(args, progress)
    progress.done([args.out])
    if args.progress != "jsonl":
        print(f"{args.out}: estimated poses of {len(doc['scans'])} scan(s) (KISS-ICP)")
    return 0


def _estimate_document(args: argparse.Namespace, progress) -> dict:
    import numpy as np

    from hgca_core.io.atomic import atomic_write
    from hgca_core.io.odometry import estimate, frame_times
    from hgca_core.io.paths import check_outputs
    from hgca_core.io.sequence import Sequence, is_sequence, open_sequence, parse_frames

    inputs = _expand(args.sequence)
    if is_sequence(inputs):
        if args.fmt is not None:
            raise InputError("--format applies to scan files, not to a sequence folder", inputs[0])
        seq = open_sequence(inputs[0], topic=args.topic, own_poses=False)
        readable = [inputs[0]] if seq.reader is not None else list(seq.files)
    else:
        if args.topic is not None:
            raise InputError("--topic applies to a ROS bag (.bag, .mcap, .db3 or a ROS 2 bag folder)", inputs[0])
        seq = Sequence("files", os.path.dirname(os.path.abspath(inputs[0])), tuple(inputs), None, args.fmt)
        readable = list(inputs)
    check_outputs([args.out], readable)        # an old poses.json beside the sweeps is no input here
    idx = list(range(len(seq))) if args.frames is None else parse_frames(args.frames, len(seq), seq.root)
    names = [seq.files[i] for i in idx]
    scans = _Frames(seq, idx)
    times = getattr(seq, "times", None)
    times = [times[i] for i in idx] if times is not None else frame_times(names, _kitti_root(seq))
    found = estimate(scans, times, names, lambda i, n: progress("odometry", i, n, os.path.basename(names[i - 1])))
    out_dir = os.path.dirname(os.path.abspath(args.out))
    entries = []
    for name, pose in zip(names, found.poses):
        entries.append({"file": _relative(name, out_dir), "pose": np.asarray(pose, dtype=np.float64).tolist()})
    doc = {"layout": seq.layout, "sequence": os.path.abspath(seq.root), "scans": entries,
           "estimated": found.record()}
    text = json.dumps(doc, indent=1).encode("utf-8")
    atomic_write(args.out, lambda f: f.write(text))
    return doc


class _Frames(SequenceABC):
    """The chosen frames, each read when the odometry gets to it (a long drive would not fit in memory at once);
    the last two are kept, since the odometry looks at frames 0 and 1 twice."""

    def __init__(self, seq, idx: list[int]) -> None:
        self._seq, self._idx = seq, idx
        self._kept: dict[int, object] = {}

    def __len__(self) -> int:
        return len(self._idx)

    def __getitem__(self, k):  # type: ignore[override]
        if isinstance(k, slice):
            return [self[j] for j in range(len(self))[k]]
        if k not in self._kept:
            self._kept = {j: v for j, v in self._kept.items() if j >= k - 1}
            self._kept[k] = self._seq.read_frame(self._idx[k])
        return self._kept[k]


def _expand(inputs: list[str]) -> list[str]:
    """Quoted globs expanded by hgca, in natural name order (shells differ; Windows expands none); a pattern
    that matches nothing is an InputError."""
    from hgca_core.io.sequence import natural_key

    out: list[str] = []
    for item in inputs:
        if not os.path.exists(item) and glob.has_magic(item):
            found = sorted((p for p in glob.glob(item) if os.path.isfile(p)), key=natural_key)
            if not found:
                raise InputError("pattern matches no file", item)
            out.extend(found)
        else:
            out.append(item)
    return out


def _kitti_root(seq) -> str | None:
    """The folder that would hold KITTI's times.txt."""
    return seq.root if seq.layout == "kitti" else None


def _relative(name: str, out_dir: str) -> str:
    path = os.path.abspath(name)
    try:
        return os.path.relpath(path, out_dir)
    except ValueError:  # another drive (Windows)
        return path

"""`hgca bench`: completion time and peak memory per stage, default region and 40 x w m strips."""
from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    from hgca_core.commands.arguments import add_config_arguments, add_out_argument, floats_arg

    p.add_argument("--widths", type=floats_arg("--widths", positive=True), default="40,60,80,100,120",
                   help="strip widths w (m) of 40 x w regions; '' for none")
    p.add_argument("--no-default", action="store_true", help="skip the default 38.4 x 38.4 m region")
    add_config_arguments(p, ("stage", "device", "t1", "weights", "fine_weights", "precision"))
    add_out_argument(p, "DIR", required=True,
                     help="folder for the result (<name>.json, .md and .png; the repository's pages: "
                          "benchmarks/results)")
    p.add_argument("--name", default=None, help="result file stem (default completion_<stage>_<device>)")


def run(args: argparse.Namespace) -> int:
    from hgca_core.bench import run as bench_run
    from hgca_core.errors import InputError
    from hgca_core.io.paths import check_outputs
    from hgca_core.pipeline import load_models

    from hgca_core.commands.arguments import check_device

    from hgca_core.commands.arguments import completion_config

    widths = list(args.widths)
    completion_config(args)       # every setting checked as `hgca complete` checks it, before any run
    check_device(args.device)
    name = args.name or f"completion_{args.stage}_{args.device.split(':')[0]}"
    load_models(args.stage, args.weights, args.fine_weights, "cpu")   # a bad file fails here, before any run
    out = Path(args.out)
    if not out.exists():          # a new results folder is made; what is there
        try:                      # already, a file in its place or an unwritable folder, `check_outputs` judges
            out.mkdir(parents=True)
        except OSError as exc:
            raise InputError(f"cannot make the output folder ({exc.strerror})", str(out)) from None
    check_outputs([out / f"{name}.{ext}" for ext in ("json", "md", "png")], [args.weights, args.fine_weights])
    result = bench_run(widths, not args.no_default, args.stage, args.device, args.t1, out, name,
                       precision=args.precision, weights=args.weights, fine_weights=args.fine_weights)
    from hgca_core.bench import table

    print(table(result))
    return 0

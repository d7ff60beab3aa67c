"""Coarse weights with precise BatchNorm statistics (run by hand), e.g.
`python benchmarks/precise_bn.py --source training --batches 400 --data D --out F.pt`, then score F as
`keep_sweep.py` scores variants (its `jobs`; the table with `keep_sweep.py --keeps "" --known LABEL=VAL,REAL`).

Why: the trainer's exported weights are an EMA of the parameters, but until session 15 their BatchNorm buffers were
copied from the live model, whose running statistics average its last ~10 batches (momentum 0.1) of two crops; the
coarse chain's growth on real scans follows those buffers (`hgca_core.training.precise_bn`, `bn_noise.py`).
`--source training` recomputes them for the averaged weights on training batches drawn as the trainer draws them
(what `torch.optim.swa_utils.update_bn` does for averaged weights); `--source regions` on whole train regions
along the model's own chains, as inference sees them. Neither changes a parameter.
"""
from __future__ import annotations

import argparse
import time

import torch


def add_args(p: argparse.ArgumentParser) -> None:
    """The options that say which batches set the statistics (shared with `bn_noise.py`)."""
    p.add_argument("--weights", default="hgca_core/weights/coarse.pt")
    p.add_argument("--data", required=True, nargs="+",
                   help="dataset folders whose train splits give the inputs (as the run was trained: all of them)")
    p.add_argument("--crop", type=int, default=64, help="training batches: the training crop (cells)")
    p.add_argument("--focus", type=float, default=0.5, help="training batches: share of crops near missed cells")
    p.add_argument("--free-weight", type=float, default=8.0, help="training batches: as the run was trained")
    p.add_argument("--cut-share", type=float, default=0.5, help="share of inputs cut 1.5-3 m up, as in training")
    p.add_argument("--threads", type=int, default=2)


def precise(args: argparse.Namespace, source: str, amount: int, seed: int) -> tuple[torch.nn.Module, str]:
    """The weights of `args.weights` with statistics from `amount` training batches (source "training") or whole
    train regions ("regions"), drawn with `seed`; and a line saying so."""
    from hgca_core.models.weights import load_coarse
    from hgca_core.training.coarse import CoarseTask
    from hgca_core.training.data import split_files
    from hgca_core.training.precise_bn import recompute_bn, recompute_bn_training, train_inputs

    model, _ = load_coarse(args.weights)
    data = " + ".join(args.data)
    if source == "training":
        task = CoarseTask(args.data, model.cfg, crop=args.crop, focus_share=args.focus, free_weight=args.free_weight,
                          cut_share=args.cut_share)
        recompute_bn_training(model, task, amount, seed=seed)
        return model, (f"{amount} training batches of {data} (crop {args.crop}, focus {args.focus:g}, cut "
                       f"{args.cut_share:g}, seed {seed})")
    inputs = train_inputs(split_files(args.data, "train")[:amount], model.cfg.free_space, args.cut_share, seed)
    passes = recompute_bn(model, inputs, tuple(model.cfg.grid), model.cfg.steps, seed)
    return model, f"{passes} passes of {len(inputs)} whole train regions of {data}"


def save(model: torch.nn.Module, weights: str, what: str, out: str) -> str:
    """`weights`' file with the model's BatchNorm buffers, and a note of where they came from."""
    from hgca_core.models.weights import half_state, load_file, save_file

    blob = load_file(weights)
    blob["state_dict"] = half_state(model)
    blob.setdefault("meta", {}).setdefault("notes", []).append(
        f"BatchNorm statistics recomputed (precise BN) over {what} (benchmarks/precise_bn.py)")
    return str(save_file(blob, out))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_args(p)
    p.add_argument("--source", choices=("training", "regions"), default="training")
    p.add_argument("--batches", type=int, default=400, help="--source training: batches of two crops")
    p.add_argument("--count", type=int, default=24, help="--source regions: train regions (a chain of T1 passes each)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="weights file to write (the input file with new BatchNorm buffers)")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    t = time.time()
    model, what = precise(args, args.source, args.batches if args.source == "training" else args.count, args.seed)
    save(model, args.weights, what, args.out)
    print(f"{what} in {time.time() - t:.0f} s -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""`hgca train coarse|coarse-noplanner --data DIR --minutes M [--resume]`, and `--export` to ship weights."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

STAGES = ("coarse", "coarse-noplanner")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("stage", choices=STAGES, help="which model to train (the no-planner one is the ablation)")
    p.add_argument("--data", default="data/synth", help="dataset folder with train/ and val/ splits (hgca synth --split)")
    p.add_argument("--out", default=None, help="run folder (default runs/<stage>)")
    p.add_argument("--minutes", type=float, default=10.0, help="wall-time budget of this session")
    p.add_argument("--max-steps", type=int, default=None, help="stop after this many steps (tests)")
    p.add_argument("--resume", action="store_true", help="continue from <out>/ckpt.pt")
    p.add_argument("--batch", type=int, default=2, help="chains per step (per rank under torchrun)")
    p.add_argument("--buffer", type=int, default=8, help="persistent chains kept (per rank)")
    p.add_argument("--crop", type=int, default=96, help="training crop in 20 cm cells (0 = full region)")
    p.add_argument("--channels", default=None, help="U-Net widths, e.g. 16,32,48,64,96")
    p.add_argument("--val-every", type=float, default=10.0, help="minutes between validation runs")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument("--export", action="store_true", help="after training, write hgca_core/weights/<stage>.pt")
    p.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    import torch

    from hgca_core.training.coarse import CoarseTask, default_config, run_name, weights_path
    from hgca_core.training.trainer import train

    if args.threads:
        torch.set_num_threads(args.threads)
    use_planner = args.stage == "coarse"
    out = Path(args.out or f"runs/{run_name(use_planner)}")
    cfg = default_config(use_planner)
    ckpt = out / "ckpt.pt"
    if args.resume and ckpt.exists():  # the run's own architecture wins over flags
        from hgca_core.models.gca import GCAConfig

        cfg = GCAConfig.from_dict(torch.load(ckpt, map_location="cpu", weights_only=False)["config"])
    elif args.channels:
        cfg.channels = tuple(int(c) for c in args.channels.split(","))
    task = CoarseTask(args.data, cfg, crop=args.crop or None)
    if args.minutes > 0 or args.max_steps:
        state = train(task, out, args.minutes, resume=args.resume, batch=args.batch, buffer_size=args.buffer,
                      val_every_min=args.val_every, max_steps=args.max_steps, progress=not args.no_progress)
        last_val = next((h for h in reversed(state["history"]) if h["kind"] == "val"), {})
        print(json.dumps({"step": state["step"], "elapsed_s": round(state["elapsed_s"], 1), **last_val}))
    if args.export:
        from hgca_core.models.checkpoint import save_weights
        from hgca_core.models.gca import GCAKernel

        ck = torch.load(ckpt, map_location="cpu", weights_only=False)
        module = task.build()
        module.load_state_dict(ck["model"])
        st = ck["state"]
        meta = {"kind": "coarse", "stage": args.stage, "steps": st["step"], "train_wall_s": round(st["elapsed_s"], 1),
                "sessions": st["sessions"], "data": str(args.data),
                "history_tail": [h for h in st["history"] if h["kind"] == "val"] + [h for h in st["history"] if h["kind"] == "train"][-3:],
                "crop": args.crop}
        dest = weights_path(use_planner)
        save_weights(module.model, ck["config"], dest, meta)
        from hgca_core.training.card import write_model_card

        print(f"wrote {dest} ({dest.stat().st_size / 1e6:.1f} MB) and {write_model_card()}")
    return 0

"""`hgca train STAGE --data DIR --minutes M [--resume] [--export]`: one trainer for every model.

Stages: coarse (GCA + planner), coarse-noplanner (the ablation), autoencoder (local implicit latents),
fine (cGCA upsampler; needs the autoencoder's weights). `--export` writes the shipped weights and the card.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

STAGES = ("coarse", "coarse-noplanner", "autoencoder", "fine")


def _share(text: str, open_ends: bool = False) -> float:
    """A share in [0, 1], or in (0, 1) with `open_ends` (argparse type)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (0.0 < value < 1.0 if open_ends else 0.0 <= value <= 1.0):
        raise argparse.ArgumentTypeError(f"must be {'strictly ' if open_ends else ''}between 0 and 1, got {value}")
    return value


def _infusion(text: str) -> tuple[float, float]:
    """'A0,A1': the infusion schedule alpha_t = A0 + A1 * t (argparse type); each in [0, 1]."""
    try:
        a0, a1 = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected two numbers A0,A1, got {text!r}") from None
    if not (0.0 <= a0 <= 1.0 and 0.0 <= a1 <= 1.0):
        raise argparse.ArgumentTypeError(f"A0 and A1 must lie in [0, 1], got {text!r}")
    return a0, a1


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("stage", choices=STAGES, help="which model to train (coarse-noplanner is the planner ablation)")
    p.add_argument("--data", default=["data/synth"], nargs="+", metavar="DIR",
                   help="dataset folder with train/ and val/ splits (hgca synth --split); several folders: train on "
                        "the union of their train splits, validate on the first one's val split")
    p.add_argument("--out", default=None, help="run folder (default runs/<stage>)")
    p.add_argument("--minutes", type=float, default=10.0, help="wall-time budget of this session (0: only --export)")
    p.add_argument("--max-steps", type=int, default=None,
                   help="stop after this many steps of this session (a resumed run counts from where it resumes)")
    p.add_argument("--resume", action="store_true", help="continue from <out>/ckpt.pt")
    p.add_argument("--batch", type=int, default=2,
                   help="chains per step (per rank under torchrun; the paper uses 6 for coarse, 3 for fine)")
    p.add_argument("--buffer", type=int, default=8, help="persistent chains kept (per rank)")
    p.add_argument("--focus", type=_share, default=None, metavar="SHARE",
                   help="coarse: share of training crops drawn around cells the input misses 3 m or more above "
                        "the ground (facades up high, tree crowns); 0 draws every crop uniformly (default 0.5)")
    p.add_argument("--free-weight", type=float, default=None, metavar="W",
                   help="coarse with --free-space: the loss on cells the input rays saw empty (and the ground truth "
                        "leaves empty) weighs 1 + W, against growth into observed free space (default 0)")
    p.add_argument("--cut", type=_share, default=None, metavar="SHARE",
                   help="coarse: share of training inputs cut 1.5-3 m above the ground (a uniform crop, the free "
                        "space above the cut unknown), as hgca eval-real cuts real scans (default 0)")
    p.add_argument("--turn", type=_share, default=None, metavar="SHARE",
                   help="coarse: share of training inputs turned by a random yaw about the sensor (synthetic regions "
                        "run along the drive; real scans come in any frame) (default 0)")
    p.add_argument("--cut-free-loss", action="store_true", default=None,
                   help="with --cut and --free-weight: on a cut input the weight also falls on cells the uncut input "
                        "saw empty (the model does not see them; hgca eval-real counts growth there)")
    p.add_argument("--frozen-bn", action="store_true", default=None,
                   help="coarse: BatchNorm normalises by the running statistics of the --init-from weights and "
                        "never updates them (trains the function sampling runs; the affine scale and shift train)")
    p.add_argument("--distill", type=_share, default=None, metavar="MU",
                   help="coarse, with --cut: on cut inputs the target moves MU of the way from the ground truth to "
                        "the --teacher's probability (cells the rays saw empty stay empty), keeping the teacher's "
                        "restraint above a cut while whole inputs train on the ground truth (default 0)")
    p.add_argument("--distill-above", action="store_true", default=None,
                   help="with --distill: distil only the cells at and above the cut's layer; below it a cut input is "
                        "whole and keeps the ground truth")
    p.add_argument("--teacher", default=None, metavar="WEIGHTS",
                   help="with --distill: coarse weights to distil from (default: the --init-from file)")
    p.add_argument("--precision", choices=("fp32", "bf16"), default=None,
                   help="GEMM precision of the sparse convs' forward and backward passes (bf16: float32 "
                        "accumulation, weights and optimiser; see benchmarks/results/train_precision.md; "
                        "default fp32). --resume keeps the run's last --focus, --free-weight, --cut, --turn, "
                        "--frozen-bn, --distill, --distill-above, --teacher and --precision unless given again")
    p.add_argument("--crop", type=int, default=None,
                   help="training crop in the stage's cells (coarse: 20 cm, default 64; fine: 10 cm, default 64)")
    p.add_argument("--channels", default=None, help="coarse U-Net widths, e.g. 16,32,48,64,96")
    p.add_argument("--infusion", type=_infusion, default=None, metavar="A0,A1",
                   help="coarse / fine, a new run: the infusion schedule alpha_t = A0 + A1 * t (default: the "
                        "--init-from file's, else the paper's 0.15,0.005); a lower A0 trains on chains closer to "
                        "the model's own, as it samples (no infusion). A resumed run keeps its own")
    p.add_argument("--autoencoder", default=None, help="fine: autoencoder weights (default: the shipped ones)")
    p.add_argument("--lr", type=float, default=None,
                   help="Adam learning rate (default 5e-4; with --resume: the run's own, or this one from now on)")
    p.add_argument("--ema-decay", type=_decay, default=None, metavar="D",
                   help="decay of the weights' moving average that exports and validation use (default 0.999, about "
                        "the last 1,000 steps; with --resume: the run's own, or this one from now on): closer to 1 "
                        "averages over more steps, as neighbouring checkpoints swing on real scans (recipe_s32.md)")
    p.add_argument("--seed", type=int, default=None, metavar="N",
                   help="a new run's random streams: initial weights, crops, chains, infusion draws (default 0). "
                        "Runs of one recipe that differ only in the seed measure its spread between runs; a resume "
                        "continues the run's own streams and refuses another seed")
    p.add_argument("--val-every", type=float, default=10.0, help="minutes between validation runs")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (1 is fastest on a busy machine)")
    p.add_argument("--device", default="cpu",
                   help="cpu, cuda or cuda:N (under torchrun, cuda puts each rank on its own GPU, cuda:LOCAL_RANK)")
    p.add_argument("--free-space", action="store_true",
                   help="coarse / fine: observed free space (what the input rays crossed) as a model input")
    p.add_argument("--init-from", default=None, metavar="WEIGHTS",
                   help="coarse / fine: start from these weights or checkpoint (its architecture; with --free-space, "
                        "weights trained without it gain zero-initialised free-space inputs); ignored by --resume "
                        "of an existing checkpoint")
    p.add_argument("--export", nargs="?", const=True, default=None, metavar="PATH",
                   help="after training, write the trained (EMA) weights with their training record: to PATH, or "
                        "without PATH as the shipped hgca_core/weights/<stage>.pt and re-render the model card")
    p.add_argument("--best", action="store_true",
                   help="with --export: the weights of the run's best validation score (<out>/best.pt, written "
                        "whenever validation improves) instead of the last step's")
    p.add_argument("--blend-with", default=None, metavar="WEIGHTS",
                   help="coarse, with --export: write (1 - T) * WEIGHTS + T * the run's weights, a fine-tune "
                        "interpolated back toward the weights it started from (WiSE-FT; benchmarks/blend_sweep.py)")
    p.add_argument("--blend-t", type=_share, default=None, metavar="T", help="with --blend-with: the run's share")
    p.add_argument("--no-progress", action="store_true")


# recipe options: argparse name -> (key in a session's record, default of a new run)
RECIPE_OPTIONS = {"focus": ("focus_share", 0.5), "free_weight": ("free_weight", 0.0), "cut": ("cut_share", 0.0),
                  "cut_free_loss": ("cut_free_loss", False), "turn": ("turn_share", 0.0),
                  "frozen_bn": ("frozen_bn", False), "distill": ("distill", 0.0), "teacher": ("teacher", None),
                  "distill_above": ("distill_above", False),
                  "precision": ("precision", "fp32")}


def _run_file(args: argparse.Namespace, ckpt: Path) -> dict | None:
    """The run's checkpoint, read once, where it decides the task: on --resume and on an export without training."""
    if not ckpt.exists() or not (args.resume or (not args.minutes and not args.max_steps)):
        return None
    from hgca_core.models.weights import load_file

    return load_file(ckpt)


def _last_recipe(args: argparse.Namespace, run_file: dict | None) -> dict:
    """What the resumed run's last session trained with (empty for a new run)."""
    if not (args.resume and run_file is not None):
        return {}
    sessions = (run_file.get("state") or {}).get("sessions") or [{}]
    return {**sessions[-1].get("recipe", {}), "precision": sessions[-1].get("precision")}


def resolve_recipe(args: argparse.Namespace, last: dict) -> dict:
    """Fill the recipe options left out: a resumed run keeps what its last session trained with (`last`, so
    leaving an option out of a resume command does not change the recipe), a new run takes the defaults. Returns
    the options taken from the run."""
    taken = {}
    for opt, (key, default) in RECIPE_OPTIONS.items():
        if getattr(args, opt) is None:
            value = last.get(key)
            if value is not None:
                taken[opt] = value
            setattr(args, opt, default if value is None else value)
    return taken


def _init_config(args: argparse.Namespace) -> dict | None:
    """The architecture of the --init-from file (weights or checkpoint), or None without one."""
    if not getattr(args, "init_from", None):
        return None
    from hgca_core.errors import InputError
    from hgca_core.models.weights import load_file

    if args.stage == "autoencoder":
        raise InputError("--init-from is for the coarse and fine stages")
    config = load_file(args.init_from).get("config")
    if not isinstance(config, dict):
        raise InputError("no model config in the file: not hgca weights or a training checkpoint", args.init_from)
    return config


def _teacher(args: argparse.Namespace, cfg, recorded: str | None) -> tuple[str, str] | None:
    """The --distill teacher's path and sha256, checked: coarse weights of the same architecture and inputs and,
    on a resume that takes the teacher from the run, the same file the run started with, `recorded` its digest
    then (shipping a fine-tune overwrites the weights it was distilled from, and a resume must not quietly distil
    from the student)."""
    from hgca_core.errors import InputError

    if not args.distill:
        if args.teacher:
            raise InputError("--teacher names the weights --distill distils from: give --distill too", args.teacher)
        if args.distill_above:
            raise InputError("--distill-above says where --distill acts: give --distill too")
        return None
    from hgca_core.io.digest import file_digest
    from hgca_core.models.weights import load_coarse

    if not args.cut or not cfg.free_space:
        raise InputError("--distill acts on cut inputs with the free space: it needs --cut and --free-space "
                         "(or weights with it)")
    path = args.teacher or args.init_from
    if not path:
        raise InputError("--distill needs a teacher: give --teacher WEIGHTS (or --init-from)")
    digest = file_digest(path)
    if recorded and digest != recorded:
        raise InputError(f"the run distilled from this teacher when its sha256 was {recorded[:12]}; the file is "
                         f"now {digest[:12]} (overwritten since?): restore it, or give --teacher again to distil "
                         "from the file as it is", path)
    teacher = load_coarse(path)[0]
    if teacher.cfg.use_planner != cfg.use_planner or teacher.cfg.free_space != cfg.free_space:
        raise InputError("the --distill teacher must be a coarse model with the trained model's planner and "
                         "free-space inputs", path)
    return str(Path(path).resolve()), digest


def build_task(args: argparse.Namespace, run_file: dict | None, teacher_sha256: str | None = None):
    """The task for the stage; a resumed run (and an export without training) keeps the architecture the run
    was started with, a run started --init-from takes the file's architecture (with --free-space switched on when
    asked). `teacher_sha256`: the digest a resumed run recorded for the teacher it takes from the run."""
    saved = run_file["config"] if run_file is not None else None
    init = None if saved else _init_config(args)
    free = bool(getattr(args, "free_space", False))
    infusion = getattr(args, "infusion", None)
    if infusion is not None and (saved or args.stage == "autoencoder"):
        from hgca_core.errors import InputError

        raise InputError("--infusion sets a new coarse or fine run's schedule; a resumed run keeps its own"
                         if saved else "--infusion is for the coarse and fine stages (the autoencoder has no chain)")
    if args.stage.startswith("coarse"):
        from hgca_core.models.gca import GCAConfig
        from hgca_core.training.coarse import CoarseTask

        if saved:
            cfg = GCAConfig.from_dict(saved)
        elif init:
            cfg = GCAConfig.from_dict({**init, "free_space": free or bool(init.get("free_space"))})
            if cfg.use_planner != (args.stage == "coarse"):
                from hgca_core.errors import InputError

                raise InputError(f"--init-from: these weights are a model {'with' if cfg.use_planner else 'without'} "
                                 f"the planner, not a {args.stage} model", args.init_from)
        else:
            cfg = GCAConfig(use_planner=args.stage == "coarse", free_space=free)
        if args.channels and not saved and not init:
            cfg.channels = tuple(int(c) for c in args.channels.split(","))
        if infusion is not None:
            cfg.alpha0, cfg.alpha1 = infusion
        if args.free_weight < 0 or (args.free_weight and not cfg.free_space):
            from hgca_core.errors import InputError

            raise InputError(f"--free-weight must be 0 or more, got {args.free_weight}" if args.free_weight < 0
                             else "--free-weight needs the free space: add --free-space (or weights with it)")
        if args.cut_free_loss and not (args.cut and args.free_weight):
            from hgca_core.errors import InputError

            raise InputError("--cut-free-loss weighs cut inputs' losses: it needs --cut and --free-weight")
        if args.frozen_bn and not (args.init_from or saved):
            from hgca_core.errors import InputError

            raise InputError("--frozen-bn keeps the running statistics of the weights a run starts from: it needs "
                             "--init-from (or --resume of a run with a checkpoint)")
        teacher, teacher_sha256 = _teacher(args, cfg, teacher_sha256) or (None, None)
        return CoarseTask(args.data, cfg, crop=args.crop or 64, focus_share=args.focus,
                          free_weight=args.free_weight, cut_share=args.cut, cut_free_loss=bool(args.cut_free_loss),
                          turn_share=args.turn, frozen_bn=bool(args.frozen_bn), distill=args.distill,
                          teacher=teacher, teacher_sha256=teacher_sha256, distill_above=bool(args.distill_above))
    if args.stage == "autoencoder":
        from hgca_core.models.autoencoder import AutoencoderConfig
        from hgca_core.training.fine import AutoencoderTask

        if free:
            from hgca_core.errors import InputError

            raise InputError("--free-space is for the coarse and fine stages (the autoencoder does not see it)")
        return AutoencoderTask(args.data, AutoencoderConfig.from_dict(saved) if saved else AutoencoderConfig())
    from hgca_core.models.cgca import CGCAConfig
    from hgca_core.models.weights import shipped
    from hgca_core.training.fine import FineTask

    if saved:
        cfg = CGCAConfig.from_dict(saved)
    elif init:
        cfg = CGCAConfig.from_dict({**init, "free_space": free or bool(init.get("free_space"))})
    else:
        cfg = CGCAConfig(free_space=free)
    if args.crop and not saved:
        cfg.crop = args.crop
    if infusion is not None:
        cfg.alpha0, cfg.alpha1 = infusion
    return FineTask(args.data, cfg, autoencoder=args.autoencoder or str(shipped("autoencoder")))


def _decay(text: str) -> float:
    """A moving-average decay, strictly between 0 and 1 (argparse type)."""
    return _share(text, open_ends=True)


def run(args: argparse.Namespace) -> int:
    import torch

    from hgca_core.errors import InputError
    from hgca_core.hardware import resolve_device
    from hgca_core.training.trainer import BEST, train

    resolve_device(args.device)   # a bad --device fails before any data is read
    if args.best and not args.export:
        raise InputError("--best goes with --export")
    if (args.blend_with is None) != (args.blend_t is None) or (args.blend_with and not args.export):
        raise InputError("--blend-with and --blend-t go together, with --export")
    if args.blend_with and not args.stage.startswith("coarse"):
        raise InputError("--blend-with is for the coarse stages")
    if args.threads:
        torch.set_num_threads(args.threads)
    out = Path(args.out or f"runs/{args.stage.replace('-', '_')}")
    ckpt = out / "ckpt.pt"
    run_file = _run_file(args, ckpt)
    last = _last_recipe(args, run_file)
    taken = resolve_recipe(args, last)
    if taken:
        said = []
        for k, v in taken.items():
            flag = f"--{k.replace('_', '-')}"
            said.append((flag if v else f"no {flag}") if isinstance(v, bool) else f"{flag} {v}")
        print("resuming with the run's " + ", ".join(said), file=sys.stderr)
    # a teacher taken from the run must still be the file the run distilled from (`_teacher` checks)
    task = build_task(args, run_file, teacher_sha256=last.get("teacher_sha256") if "teacher" in taken else None)
    del run_file   # the trainer reads the checkpoint itself (optimiser, chains)
    if args.minutes > 0 or args.max_steps:
        state = train(task, out, args.minutes, resume=args.resume, batch=args.batch, buffer_size=args.buffer,
                      val_every_min=args.val_every, max_steps=args.max_steps, progress=not args.no_progress,
                      device=args.device, init_from=args.init_from, precision=args.precision, lr=args.lr,
                      ema_decay=args.ema_decay, seed=args.seed)
        last_val = next((h for h in reversed(state["history"]) if h["kind"] == "val"), {})
        print(json.dumps({"step": state["step"], "elapsed_s": round(state["elapsed_s"], 1), **last_val}))
    if args.export:
        if args.best and not (out / BEST).exists():
            raise InputError(f"no {BEST} in {out}: the run has not validated since best-score weights were kept; "
                             "train on (a validation writes it) or export the last step without --best")
        print(f"wrote {export(args, task, out / BEST if args.best else ckpt)}")
    return 0


def export(args: argparse.Namespace, task, ckpt: Path) -> Path:
    """Weights from the run's checkpoint, with its training record as metadata: to `--export PATH`, or as the
    shipped file of the stage and then the card."""
    from hgca_core.models.weights import WEIGHTS_DIR, shipped
    from hgca_core.training.card import write_model_card

    target = Path(shipped(args.stage) if args.export is True else args.export)
    extra = {"stage": args.stage, "data": " + ".join(map(str, args.data))}
    if args.stage.startswith("coarse"):
        from hgca_core.models.weights import load_file, save_weights, trained_weights
        from hgca_core.training.trainer import run_record

        ck = load_file(ckpt)
        module = task.build()
        module.load_state_dict(trained_weights(ck))
        meta = {**run_record(ck), **extra, "crop": task.crop}
        if args.blend_with:
            from hgca_core.models.weights import blend_files, save_file

            with tempfile.TemporaryDirectory() as tmp:
                run_weights = save_weights(Path(tmp) / f"{ckpt.parent.name}.pt", module.model, meta)
                blob = blend_files(args.blend_with, run_weights, args.blend_t)
            from hgca_core.io.digest import file_digest

            blob["meta"]["blend"]["b"].update(file=str(ckpt), sha256=file_digest(ckpt))   # not the temporary file
            dest = save_file(blob, target)
        else:
            dest = save_weights(target, module.model, meta)
    elif args.stage == "autoencoder":
        from hgca_core.training.fine import export_autoencoder

        dest = export_autoencoder(ckpt, target, meta=extra)
    else:
        from hgca_core.training.fine import export_fine

        dest = export_fine(ckpt, args.autoencoder or shipped("autoencoder"), target, meta=extra)
    if Path(dest).resolve().parent == WEIGHTS_DIR.resolve():   # weights beside the card: the card follows them
        write_model_card()
    return Path(dest)

"""`hgca train --recipe NAME [--set key=value ...] --data DIR --minutes M [--resume] [--export [PATH]]`.

One trainer for every model; what a run trains with is a named recipe (`hgca_core.training.recipes.RECIPES`,
e.g. `coarse-shipped`, the one behind the shipped coarse weights) with `--set` overrides. The resolved recipe
is saved in the checkpoint: `--resume` continues it as saved, changed only by the `--set` fields given again
(each change printed). `--export` writes the weights the run selected on val (the average at its best validation
score, `training.selection`) with their training record; without a path, as the stage's shipped file, and the model
card follows.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
from pathlib import Path

from hgca_core.commands.arguments import (add_config_arguments, add_out_argument, add_seed_argument,
                                          add_threads_argument, counted)
from hgca_core.errors import InputError
from hgca_core.training.recipes import DEFAULT, RECIPES, Recipe, parse_sets, resolve, resumed

MAX_MINUTES = 525_600.0       # a year of wall time
MAX_STEPS = 1_000_000_000


def _minutes(text: str) -> float:
    """`--minutes`: a finite number of minutes, 0 (export only) up to a year (argparse type)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(value) and 0.0 <= value <= MAX_MINUTES):
        raise argparse.ArgumentTypeError(f"must be a finite number of minutes between 0 and {MAX_MINUTES:g}, "
                                         f"got {text!r}")
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--recipe", default=None, choices=list(RECIPES), metavar="NAME",
                   help=f"the named training recipe ({', '.join(RECIPES)}; default {DEFAULT}); *-shipped ones "
                        "made the shipped weights and start from them")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="sets",
                   help="override one recipe field (repeatable), e.g. --set lr=1e-4 --set batch=4; unknown keys "
                        "and out-of-range values are refused. With --resume: change the saved recipe from now on")
    p.add_argument("--data", default=["data/synth"], nargs="+", metavar="DIR",
                   help="dataset folder with train/ and val/ splits (hgca synth --split); several folders: train on "
                        "the union of their train splits, validate on the first one's val split")
    add_out_argument(p, "DIR", required=True, help="run folder (its checkpoint, logs and recipe)")
    p.add_argument("--minutes", type=_minutes, default=10.0,
                   help="wall-time budget of this invocation (0: no training, only --export of the run)")
    p.add_argument("--max-steps", type=counted(1, MAX_STEPS), default=None, metavar="N",
                   help="stop after this many steps of this invocation (a resumed run counts from where it resumes)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out (its checkpoint, with the recipe saved in it)")
    add_config_arguments(p, ("device",), device={"help": "cpu, cuda or cuda:N (under torchrun, cuda puts each rank "
                                                         "on its own GPU, cuda:LOCAL_RANK)"})
    add_threads_argument(p, "torch CPU threads (1 is fastest on a busy machine)")
    add_seed_argument(p, "a new run's random streams: initial weights, crops, chains, infusion draws (default 0); "
                         "a resume continues the run's own streams and refuses another seed", default=None)
    p.add_argument("--export", nargs="?", const=True, default=None, metavar="PATH",
                   help="after training, write the run's weights selected on val (the average at its best "
                        "validation score, best.pt; a run without one: its last checkpoint's) with their training "
                        "record: to PATH, or without PATH as the shipped hgca_core/weights/<stage>.pt and re-render "
                        "the model card")
    p.add_argument("--no-progress", action="store_true", help="no progress bar: one JSON log line per 10 steps")


def _saved_recipe(ck: dict, ckpt: Path) -> tuple[dict, str]:
    saved = ck.get("recipe")
    if not isinstance(saved, dict) or "fields" not in saved:
        raise InputError("the checkpoint holds no saved recipe (written before recipes were saved): train it on "
                         "from its weights as a new run, --set init_from=" + str(ckpt), ckpt)
    return saved["fields"], str(saved.get("name", "?"))


def plan(args: argparse.Namespace) -> tuple[str, Recipe, dict | None, Path]:
    """(recipe name, resolved recipe, the run's checkpoint where this command continues it, run folder): every
    argument and path checked before any work."""
    from hgca_core.dataset.samples import split_files
    from hgca_core.training.trainer import BEST

    sets = parse_sets(args.sets)
    if args.minutes == 0 and not args.export:
        raise InputError("--minutes 0 trains nothing: give a budget, or --export to export the run only")
    if args.minutes == 0 and args.max_steps:
        raise InputError("--max-steps with --minutes 0: a session of 0 minutes runs no step; give a budget")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError("--out names a run folder, and this is a file", out)
    ckpt = out / "ckpt.pt"
    continuing = args.resume or args.minutes == 0
    run_file = None
    if continuing and ckpt.exists():
        from hgca_core.models.weights import load_file

        run_file = load_file(ckpt)
        fields, name = _saved_recipe(run_file, ckpt)
        if args.recipe is not None and args.recipe != name:
            raise InputError(f"the run in --out was trained with the recipe {name}, not {args.recipe}: leave out "
                             "--recipe (a resume keeps its own) or start another --out", out)
        recipe, changed = resumed(fields, sets)
        if changed:
            said = ", ".join(f"{k} {now!r} (was {was!r})" for k, (was, now) in changed.items())
            print(f"resuming the run's recipe {name} with {said}", file=sys.stderr)
        args.recipe = name
    else:
        args.recipe = args.recipe or DEFAULT
        recipe = resolve(args.recipe, sets)
        if args.minutes == 0:
            raise InputError("nothing to export: no checkpoint in the run folder (train it first)", out)
        if not continuing and ckpt.exists():
            raise InputError("--out already holds a run (ckpt.pt): give --resume to continue it, or another --out",
                             out)
        if (out / BEST).exists():   # an export of the new run would ship it until the run's first validation
            raise InputError(f"--out holds the {BEST} of an earlier run without its checkpoint: move it away, or "
                             "give another --out", out / BEST)
        if args.resume:
            print(f"no checkpoint at {ckpt}: starting a new run of the recipe {args.recipe}", file=sys.stderr)
    split_files(args.data, "train")   # every split the run reads, before any work
    split_files(args.data, "val")
    for what in ("init_from", "autoencoder"):
        path = getattr(recipe, what)
        if path and run_file is None and not Path(path).is_file():
            raise InputError(f"recipe field {what}: no such weights file", path)
    _check_outputs(args, recipe, out)
    return args.recipe, recipe, run_file, out


def _check_outputs(args: argparse.Namespace, recipe: Recipe, out: Path) -> None:
    """The run folder can be made and written, and no output replaces an input: a dataset's files, the
    autoencoder, the run's own checkpoint (an export reads it). Exporting over `init_from` is allowed: that is
    how a fine-tune of the shipped weights ships, and a resume refuses a teacher whose file changed since."""
    from hgca_core.io.paths import check_outputs

    probe = out
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise InputError("cannot create or write the run folder here", probe)
    if args.export:
        from hgca_core.models.weights import shipped
        from hgca_core.training.trainer import BEST

        target = shipped(recipe.stage) if args.export is True else Path(args.export)
        inputs = [*args.data, recipe.autoencoder, out / "ckpt.pt", out / BEST]
        check_outputs([target], inputs)
        args.export_to = target


def _teacher(recipe: Recipe, cfg, recorded: str | None) -> tuple[str, str] | tuple[None, None]:
    """The distillation teacher (the `init_from` weights): path and sha256, checked to be coarse weights with the
    trained model's planner and inputs and, on a resume, the very file the run started distilling from (shipping
    a fine-tune overwrites the weights it was distilled from; a resume must not quietly distil from the student)."""
    if not recipe.distill:
        return None, None
    from hgca_core.io.digest import file_digest
    from hgca_core.models.weights import load_coarse

    path = recipe.init_from
    digest = file_digest(path)
    if recorded and digest != recorded:
        raise InputError(f"the run distilled from this teacher when its sha256 was {recorded[:12]}; the file is "
                         f"now {digest[:12]} (overwritten since?): restore it, or start a new run", path)
    teacher = load_coarse(path)[0]
    if teacher.cfg.use_planner != cfg.use_planner or teacher.cfg.free_space != cfg.free_space:
        raise InputError("recipe field distill: init_from must be a coarse model with the trained model's planner "
                         "and free-space inputs", path)
    return str(Path(path).resolve()), digest


def _schedule(cfg, recipe: Recipe) -> None:
    """A new run's chain length and infusion slope from the recipe (a few-step student's), in the model config
    its weights carry: sampling reads T from there."""
    if recipe.steps is not None:
        cfg.steps = recipe.steps
    if recipe.alpha1 is not None:
        cfg.alpha1 = recipe.alpha1


def build_task(recipe: Recipe, data: list[str], run_file: dict | None = None):
    """The task of the recipe's stage. A continued run keeps the architecture it was started with; a run started
    from `init_from` takes the file's architecture (with the free space switched on when the recipe asks)."""
    from hgca_core.models.weights import load_file

    saved = run_file["config"] if run_file is not None else None
    init = None
    if not saved and recipe.init_from:
        init = load_file(recipe.init_from).get("config")
        if not isinstance(init, dict):
            raise InputError("no model config in the file: not hgca weights or a training checkpoint",
                             recipe.init_from)
        init = {**init, "free_space": recipe.free_space or bool(init.get("free_space"))}
    if recipe.coarse:
        from hgca_core.models.gca import GCAConfig
        from hgca_core.training.coarse import CoarseTask

        cfg = GCAConfig.from_dict(saved or init) if (saved or init) else \
            GCAConfig(use_planner=recipe.stage == "coarse", free_space=recipe.free_space)
        if recipe.channels and not (saved or init):
            cfg.channels = tuple(recipe.channels)
        if not saved:
            _schedule(cfg, recipe)
        if cfg.use_planner != (recipe.stage == "coarse"):
            raise InputError(f"recipe field init_from: these weights are a model "
                             f"{'with' if cfg.use_planner else 'without'} the planner, not a {recipe.stage} model",
                             recipe.init_from)
        if recipe.free_weight and not cfg.free_space:
            raise InputError("recipe field free_weight needs the free space: --set free_space=true")
        recorded = None
        if run_file is not None:
            recorded = ((run_file.get("state") or {}).get("sessions") or [{}])[-1].get("recipe", {}).get(
                "teacher_sha256")
        teacher, digest = _teacher(recipe, cfg, recorded)
        return CoarseTask(data, cfg, crop=recipe.crop, focus_share=recipe.focus, free_weight=recipe.free_weight,
                          cut_share=recipe.cut, cut_free_loss=recipe.cut_free_loss, turn_share=recipe.turn,
                          distill=recipe.distill, teacher=teacher, teacher_sha256=digest)
    if recipe.stage == "semantics":
        from hgca_core.models.semantics import SemanticsConfig
        from hgca_core.training.semantics import SemanticsTask

        cfg = SemanticsConfig.from_dict(saved) if saved else SemanticsConfig(placement=recipe.placement or "geometry")
        return SemanticsTask(data, cfg, crop=recipe.crop)
    if recipe.stage == "autoencoder":
        from hgca_core.models.autoencoder import AutoencoderConfig
        from hgca_core.training.fine import AutoencoderTask

        cfg = AutoencoderConfig.from_dict(saved) if saved else AutoencoderConfig(crop=recipe.crop)
        return AutoencoderTask(data, cfg)
    from hgca_core.models.cgca import CGCAConfig
    from hgca_core.models.weights import shipped
    from hgca_core.training.fine import FineTask

    cfg = CGCAConfig.from_dict(saved or init) if (saved or init) else CGCAConfig(free_space=recipe.free_space)
    if not saved:
        cfg.crop = recipe.crop
        _schedule(cfg, recipe)
    return FineTask(data, cfg, autoencoder=recipe.autoencoder or str(shipped("autoencoder")))


def run(args: argparse.Namespace) -> int:
    import torch

    from hgca_core.hardware import resolve_device
    from hgca_core.training.trainer import train

    resolve_device(args.device)   # a GPU this machine lacks fails before any data is read
    name, recipe, run_file, out = plan(args)
    if args.threads:
        torch.set_num_threads(args.threads)
    task = build_task(recipe, args.data, run_file)
    del run_file   # the trainer reads the checkpoint itself (optimiser, chains)
    if args.minutes > 0:
        state = train(task, out, args.minutes, resume=args.resume, batch=recipe.batch, buffer_size=recipe.buffer,
                      val_every_min=recipe.val_every, max_steps=args.max_steps, progress=not args.no_progress,
                      device=args.device, init_from=recipe.init_from, precision=recipe.precision, lr=recipe.lr,
                      seed=args.seed, recipe={"name": name, "fields": recipe.to_dict()})
        last_val = next((h for h in reversed(state["history"]) if h["kind"] == "val"), {})
        print(json.dumps({"step": state["step"], "elapsed_s": round(state["elapsed_s"], 1), **last_val}))
    if args.export:
        print(f"wrote {export(recipe, args.data, task, out / 'ckpt.pt', args.export_to)}")
    return 0


def export(recipe: Recipe, data: list[str], task, ckpt: Path, target: Path) -> Path:
    """The run's weights as it selected them on val (`training.selection.selected_run`: the average kept at the
    best validation score, best.pt, else the checkpoint's), with its training record as metadata (blended back
    toward `init_from` when the recipe says so); weights written beside the model card re-render it."""
    from hgca_core.models.weights import WEIGHTS_DIR, shipped, trained_weights
    from hgca_core.training.export import save_weights

    extra = {"stage": recipe.stage, "data": " + ".join(map(str, data))}
    if recipe.coarse:
        from hgca_core.training.selection import selected_run

        ck, record, source = selected_run(ckpt)
        module = task.build()
        module.load_state_dict(trained_weights(ck))
        meta = {**record, **extra, "crop": task.crop}
        if recipe.blend is not None:
            from hgca_core.io.digest import file_digest
            from hgca_core.models.weights import save_file
            from hgca_core.training.export import blend_files

            with tempfile.TemporaryDirectory() as tmp:
                run_weights = save_weights(Path(tmp) / f"{ckpt.parent.name}.pt", module.model, meta)
                blob = blend_files(recipe.init_from, run_weights, recipe.blend)
            # the run's own file, not the temporary one, and the val selection the run's part was taken at
            blob["meta"]["blend"]["b"].update(file=str(source), sha256=file_digest(source),
                                              **({"selected": record["selected"]} if "selected" in record else {}))
            dest = save_file(blob, target)
        else:
            dest = save_weights(target, module.model, meta)
    elif recipe.stage == "semantics":
        from hgca_core.training.semantics import export_semantics

        dest = export_semantics(ckpt, target, meta=extra)
    elif recipe.stage == "autoencoder":
        from hgca_core.training.fine import export_autoencoder

        dest = export_autoencoder(ckpt, target, meta=extra)
    else:
        from hgca_core.training.fine import export_fine

        dest = export_fine(ckpt, recipe.autoencoder or shipped("autoencoder"), target, meta=extra)
    if Path(dest).resolve().parent == WEIGHTS_DIR.resolve():   # weights beside the card: the card follows them
        from hgca_core.training.card import write_model_card

        write_model_card()
    return Path(dest)

"""The one training loop of both stages: time budget, exact resume, atomic checkpoints, DDP, weight EMA.

A task (coarse or fine) supplies the loss module, fresh examples for the chain buffer and a validation
metric. The loop trains until its time budget is spent, then checkpoints, so training can continue across
sessions with `--resume`. Under `torchrun` every rank keeps its own chains; gradients are all-reduced by
DistributedDataParallel (gloo on CPU, NCCL on GPUs, one GPU per rank) and rank 0 writes checkpoints (with
every rank's chains and random streams) and logs.

Validation and the shipped weights use an exponential moving average of the weights: with Adam at a constant
5e-4 (the paper's setting) consecutive checkpoints of the coarse model differed by up to 0.24 validation IoU;
the average removes that step-to-step noise.
"""
from __future__ import annotations

import copy
import json
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
import torch.distributed as dist
from torch import nn
from tqdm import tqdm

from hgca_core.errors import InputError
from hgca_core.hardware import cpu_name, device_name, resolve_device
from hgca_core.io.atomic import atomic_write
from hgca_core.models.weights import load_file, save_file
from hgca_core.nn.conv import training_precision
from hgca_core.training.buffer import Chain, ChainBuffer

LR = 5e-4  # Adam's learning rate unless a run is given another (`hgca train --lr`)


class Task(Protocol):
    name: str
    cfg: Any

    def build(self) -> nn.Module: ...
    def new_example(self, rng: np.random.Generator) -> Chain: ...
    def validate(self, loss_module: nn.Module, seed: int = 0) -> dict: ...


EMA_DECAY = 0.999   # the weight average's default: about the last 1,000 steps


class EMA:
    """Exponential moving average of a module's weights and floating buffers (integer ones, e.g. BatchNorm's batch
    count, are copied), with the usual warm-up decay min(decay, (1 + n) / (10 + n)) so short runs are averaged
    over their own steps only. BatchNorm's running statistics are averaged too (as `AveragedModel(use_buffers=True)`
    does): copied, they are the live model's last ~10 batches, and the coarse chain's growth on real scans swung
    with them from one checkpoint to the next."""

    def __init__(self, module: nn.Module, decay: float = EMA_DECAY) -> None:
        self.decay, self.n = decay, 0
        self.module = copy.deepcopy(module).eval()
        for p in self.module.parameters():
            p.requires_grad_(False)

    @torch.no_grad()
    def update(self, module: nn.Module) -> None:
        d = min(self.decay, (1 + self.n) / (10 + self.n))
        for e, p in zip(self.module.parameters(), module.parameters()):
            e.lerp_(p.detach(), 1.0 - d)
        for e, b in zip(self.module.buffers(), module.buffers()):
            if e.is_floating_point():
                e.lerp_(b, 1.0 - d)
            else:
                e.copy_(b)
        self.n += 1

    def state_dict(self) -> dict:
        return {"n": self.n, "decay": self.decay, "model": self.module.state_dict()}

    def load_state_dict(self, d: dict) -> None:
        self.n, self.decay = d["n"], d["decay"]
        self.module.load_state_dict(d["model"])


def run_record(ck: dict) -> dict:
    """What shipped weights record of the run that made them (the model card renders it): steps, summed step
    time, sessions, notes, the samples any session trained on, validation history and the last training logs."""
    st = ck["state"]
    return {"steps": st["step"], "train_wall_s": round(st["elapsed_s"], 1), "sessions": st["sessions"],
            "seed": int(st.get("seed", 0)),
            "notes": st.get("notes", []), **({"init": st["init"]} if "init" in st else {}),
            "train_samples": sorted({n for ses in st["sessions"] for n in ses.get("train_samples", [])}),
            "history_tail": [h for h in st["history"] if h["kind"] == "val"]
            + [h for h in st["history"] if h["kind"] == "train"][-3:]}


class _StopOnSignal:
    """Ctrl-C / SIGTERM end training after the current step, with validation and a checkpoint, like the end of
    the time budget; a second signal interrupts at once."""

    def __init__(self) -> None:
        self.flag = False
        self.saved = {}
        if threading.current_thread() is threading.main_thread():
            self.saved = {sig: signal.signal(sig, self._handle) for sig in (signal.SIGINT, signal.SIGTERM)}

    def _handle(self, signum: int, frame: object) -> None:
        if self.flag:
            raise KeyboardInterrupt
        self.flag = True
        print(f"{signal.Signals(signum).name}: stopping after this step (checkpoint follows)", flush=True)

    def __enter__(self) -> "_StopOnSignal":
        return self

    def __exit__(self, *exc: object) -> None:
        """Give the handlers back however the loop ends, an exception included."""
        for sig, handler in self.saved.items():
            signal.signal(sig, handler)
        self.saved = {}


def _dist(device: str) -> tuple[int, int, torch.device]:
    """(rank, world size, this rank's device). Under torchrun a CUDA run puts rank r on cuda:LOCAL_RANK and
    uses NCCL; a CPU run uses gloo (whether or not the machine has a GPU)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    local = int(os.environ.get("LOCAL_RANK", "0")) if world > 1 else None
    dev = resolve_device(device, local)
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if dev.type == "cuda" else "gloo")
    if dist.is_initialized():
        return dist.get_rank(), dist.get_world_size(), dev
    return 0, 1, dev


def _stream_seed(seed: int, rank: int, step: int) -> int:
    """A seed for a rank that has no saved stream (a run resumed on more ranks than it was saved with)."""
    return int(np.random.SeedSequence([seed, rank, step]).generate_state(1)[0])


def _rng_state(device: torch.device) -> dict:
    """This rank's torch generators as tensors (the CPU one, and the device's on a GPU)."""
    return {"torch": torch.get_rng_state(),
            "cuda": torch.cuda.get_rng_state(device) if device.type == "cuda" else None}


def _set_rng_state(d: dict, device: torch.device) -> None:
    torch.set_rng_state(d["torch"])
    if device.type == "cuda" and d.get("cuda") is not None:
        torch.cuda.set_rng_state(d["cuda"], device)


def _gather(obj: dict, rank: int, world: int) -> list[dict] | None:
    """Every rank's `obj` on rank 0 (None elsewhere); one process: [obj]."""
    if world == 1:
        return [obj]
    out: list | None = [None] * world if rank == 0 else None
    dist.gather_object(obj, out, dst=0)
    return out


def train(task: Task, out_dir: str | Path, minutes: float, resume: bool = False, batch: int = 2,
          buffer_size: int = 8, lr: float | None = None, clip: float = 0.5, seed: int | None = None,
          val_every_min: float = 10.0, ckpt_every_min: float = 5.0, max_steps: int | None = None,
          progress: bool = True, device: str = "cpu", init_from: str | os.PathLike | None = None,
          precision: str = "fp32", recipe: dict | None = None) -> dict:
    """Train `task` for `minutes` of wall time (or `max_steps`), resuming from out_dir/ckpt.pt if asked.

    `device` 'cuda' trains on the GPU (each torchrun rank on its own, cuda:LOCAL_RANK): the model, its optimiser
    state, the weight average and the chain buffer live there. Every rank draws from its own random streams
    (torch seeded with seed + rank, numpy with seed + 7919 rank) and the checkpoint keeps each rank's streams
    and chains, so a resumed run continues every rank where it stopped: one process resumed gives bit for bit
    the run that never stopped. Validation runs on rank 0 on the CPU (it meshes and measures with numpy / scipy).

    `seed` (default 0) starts a new run's streams (initial weights, crops, chains, infusion draws) and is recorded;
    runs of one recipe that differ only in it measure the recipe's spread. A resume continues the run's own
    streams: a different `seed` there is refused rather than silently ignored.

    `precision` 'bf16' runs the sparse convs' forward and backward GEMMs in bfloat16 (float32 accumulation,
    weights, gradients and optimiser state; `nn.conv.training_precision`); validation stays float32.

    `lr`: Adam's learning rate (None: LR, or the resumed checkpoint's own); given on a resume it replaces the
    checkpoint's from this step on (an annealing phase), which the run's notes record.

    `init_from` (weights or a checkpoint of the task's kind) initialises a run that does not resume a checkpoint
    (`training.export.load_into`: new free-space inputs start at zero); the run's notes record it.

    `recipe` (`hgca train`'s resolved recipe, plain values) is saved in every checkpoint, so a resume continues
    the run as it was configured, not from flags given again."""
    if precision not in ("fp32", "bf16"):
        raise InputError(f"training precision must be fp32 or bf16, not {precision!r}")
    start_seed = 0 if seed is None else int(seed)
    if start_seed < 0:
        raise InputError(f"the seed must be 0 or more, not {seed}")
    train_dtype = torch.bfloat16 if precision == "bf16" else None
    rank, world, dev = _dist(device)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / "ckpt.pt"
    torch.manual_seed(start_seed + rank)      # seeds the CPU generator and every GPU's
    module = task.build().to(dev)
    optim = torch.optim.Adam(module.parameters(), lr=LR if lr is None else lr)
    buffer = ChainBuffer(buffer_size, task.new_example, task.cfg.steps,
                         np.random.default_rng(start_seed + 7919 * rank), dev)
    state = {"step": 0, "elapsed_s": 0.0, "history": [], "sessions": [], "seed": start_seed}
    ema_state = None
    if resume and ckpt_path.exists():
        ck = load_file(ckpt_path)
        run_seed = int(ck["state"].get("seed", 0))    # runs from before the seed was recorded all used 0
        if seed is not None and int(seed) != run_seed:
            raise InputError(f"the run was started with seed {run_seed} and a resume continues its streams: leave "
                             f"out the seed (or give {run_seed}), or start a new run with seed {seed}", ckpt_path)
        module.load_state_dict(ck["model"])
        optim.load_state_dict(ck["optim"])     # moves its state to the parameters' device
        state = ck["state"]
        was = optim.param_groups[0]["lr"]
        if lr is not None and lr != was:
            for group in optim.param_groups:
                group["lr"] = lr
            state.setdefault("notes", []).append(f"learning rate {lr:g} from step {state['step']:,} on (was {was:g})")
        ranks = ck["ranks"] if "ranks" in ck else [{"rng": {"torch": ck["torch_rng"]}, "buffer": ck.get("buffer")}]
        if rank < len(ranks):
            if ranks[rank].get("buffer") is not None:
                buffer.load_state_dict(ranks[rank]["buffer"])
            _set_rng_state(ranks[rank]["rng"], dev)
        else:                                  # more ranks than the run was saved with: new streams of their own
            torch.manual_seed(_stream_seed(run_seed, rank, state["step"]))
            buffer.rng = np.random.default_rng(_stream_seed(run_seed + 1, rank, state["step"]))
        ema_state = ck.get("ema")
    else:
        if resume and rank == 0:
            print(f"no checkpoint at {ckpt_path}: starting {'from ' + str(init_from) if init_from else 'from scratch'}")
        if init_from:
            from hgca_core.models.weights import shown_path
            from hgca_core.training.export import lineage, load_into

            meta = load_into(module.model, init_from)
            state["init"] = lineage(init_from, meta)
            state.setdefault("notes", []).append(
                f"initialised from {shown_path(init_from)} ({meta.get('steps')} steps)"
                + (", its free-space inputs new and zero-initialised" if meta.get("widened") else ""))
    ema = EMA(module)     # a checkpoint from before the EMA existed starts it at its weights
    if ema_state:
        ema.load_state_dict(ema_state)
    ddp = nn.parallel.DistributedDataParallel(module, device_ids=[dev.index] if dev.type == "cuda" else None) \
        if world > 1 else module
    module.train()

    def checkpoint(session_open: bool = True) -> None:
        """Collective under DDP: every rank hands rank 0 its streams and chains. A checkpoint written while the
        session runs lists the session so far, so its steps are accounted for when the process is killed before
        the session ends or the file is exported mid-run."""
        ranks = _gather({"rng": _rng_state(dev), "buffer": buffer.state_dict()}, rank, world)
        if rank == 0:
            record = with_this_session() if session_open else state
            save_file({"model": _cpu(module.state_dict()), "optim": _cpu(optim.state_dict()), "state": record,
                       "ranks": ranks, "ema": _cpu(ema.state_dict()), "config": task.cfg.to_dict(),
                       "task": task.name, **({"recipe": recipe} if recipe is not None else {})}, ckpt_path)

    def validate() -> None:
        if rank == 0:
            model = ema.module if dev.type == "cpu" else copy.deepcopy(ema.module).cpu()
            metrics = task.validate(model)
            ema.module.eval()
            state["history"].append({"step": state["step"], "elapsed_s": round(state["elapsed_s"], 1),
                                     "kind": "val", **metrics})
            plot_history(state["history"], out / "curve.png", task.name)
            if not progress:
                print(json.dumps(state["history"][-1]), flush=True)
            keep_if_best(metrics)

    def keep_if_best(metrics: dict) -> None:
        """Write best.pt (a checkpoint without optimiser or chains: weights, average, record so far) when the
        validation score is the run's best yet. Why: a run's val score can peak mid-session and fall (74.3 % at
        40 min, 72.7 % at 80 in one fine-tune), and the checkpoint keeps only the last step."""
        key = next((k for k in VAL_KEYS if k in metrics), None)
        value = float(metrics[key]) if key else float("nan")
        best = state.get("best_val")
        if not np.isfinite(value) or (best and not _better(key, value, best["value"])):
            return
        state["best_val"] = {"key": key, "value": value, "step": state["step"]}
        save_file({"model": _cpu(module.state_dict()), "ema": _cpu(ema.state_dict()), "state": with_this_session(),
                   "config": task.cfg.to_dict(), "task": task.name,
                   **({"recipe": recipe} if recipe is not None else {})}, out / BEST)

    def with_this_session() -> dict:
        """The run's state as a file written mid-session keeps it: the session so far listed with the others."""
        return {**state, "sessions": [*state["sessions"], session_record()]}

    def session_record() -> dict:
        """This invocation of the trainer so far, as the run's record (and the model card) lists it."""
        train_files = getattr(task, "train_files", [])
        return {"ended": time.strftime("%Y-%m-%d %H:%M:%S"), "steps": steps_this_session,
                "wall_s": round(time.time() - session_start, 1), "world_size": world,
                "device": dev.type, "device_name": device_name(dev), "cpu": cpu_name(),
                "threads": torch.get_num_threads(), "precision": precision,
                "lr": optim.param_groups[0]["lr"], "batch": batch, "ema_decay": ema.decay,
                "train_samples": [Path(f).name for f in train_files],
                "train_folders": sorted({str(Path(f).parents[1]) for f in train_files}),
                "recipe": dict(getattr(task, "recipe", lambda: {})())}

    session_start = time.time()
    budget = minutes * 60.0
    last_ckpt = last_val = time.time()
    stats_acc: dict[str, list[float]] = {}
    bar = tqdm(total=round(budget), unit="s", desc=f"train {task.name}", disable=not progress or rank != 0)
    steps_this_session = 0
    with _StopOnSignal() as stop_asked:
        while True:
            # stop / validate / checkpoint are decided together on every rank (checkpoints are collective)
            now = time.time()
            flags = [now - session_start >= budget or (max_steps is not None and steps_this_session >= max_steps)
                     or stop_asked.flag, now - last_val >= val_every_min * 60, now - last_ckpt >= ckpt_every_min * 60]
            if world > 1:
                t = torch.tensor([float(f) for f in flags], device=dev)
                dist.all_reduce(t, op=dist.ReduceOp.MAX)
                flags = [bool(v) for v in t.tolist()]
            stop, val_due, ckpt_due = flags
            if stop:
                break
            if val_due and steps_this_session:
                validate()
                last_val = time.time()
            if ckpt_due and steps_this_session:
                checkpoint()
                last_ckpt = time.time()
            t0 = time.time()
            idx = buffer.take(batch)
            chains = [buffer.chains[i] for i in idx]
            with training_precision(train_dtype):
                loss, stats, new_states = ddp(chains)
                optim.zero_grad(set_to_none=True)
                loss.backward()
            torch.nn.utils.clip_grad_norm_(module.parameters(), clip)
            optim.step()
            ema.update(module)
            for i, s in zip(idx, new_states):
                buffer.advance(i, s)
            if dev.type == "cuda":
                torch.cuda.synchronize(dev)    # step times measure the work, not its queueing
            dt = time.time() - t0
            state["step"] += 1
            state["elapsed_s"] += dt
            steps_this_session += 1
            for k, v in {"loss": float(loss.detach()), **stats, "step_s": dt}.items():
                stats_acc.setdefault(k, []).append(v)
            bar.n = min(round(time.time() - session_start), round(budget))
            bar.set_postfix(step=state["step"], loss=f"{float(loss.detach()):.4f}")
            if state["step"] % 10 == 0 and rank == 0:
                state["history"].append({"step": state["step"], "elapsed_s": round(state["elapsed_s"], 1),
                                         "kind": "train", **{k: float(np.mean(v)) for k, v in stats_acc.items()}})
                stats_acc = {}
                if not progress:  # a log line for runs in the background
                    print(json.dumps(state["history"][-1]), flush=True)
    bar.close()
    validate()
    state["sessions"].append(session_record())
    checkpoint(session_open=False)
    if rank == 0:
        atomic_write(out / "history.json", lambda f: f.write(json.dumps(state["history"], indent=1).encode()))
    return state


BEST = "best.pt"                       # beside ckpt.pt: the weights of the run's best validation score
VAL_KEYS = ("val_iou", "val_cd")       # the validation score of a task: IoU (higher is better) or CD (lower)


def _better(key: str, new: float, old: float) -> bool:
    return new > old if key == "val_iou" else new < old


def _cpu(x: Any) -> Any:
    """A state dict (nested dicts / lists of tensors) with every tensor on the CPU, for the checkpoint."""
    if isinstance(x, torch.Tensor):
        return x.cpu()
    if isinstance(x, dict):
        return {k: _cpu(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_cpu(v) for v in x]
    return x


def plot_history(history: list[dict], path: Path, title: str) -> None:
    """Loss and validation IoU against steps, one PNG, so progress across sessions is visible."""
    plot_histories({title: history}, path, title)


def plot_histories(runs: dict[str, list[dict]], path: Path, title: str) -> None:
    """Several runs' loss and validation curves on shared axes (runs trained side by side on one GPU)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    key = None
    for name, history in runs.items():
        tr = [h for h in history if h["kind"] == "train"]
        va = [h for h in history if h["kind"] == "val"]
        label = name if len(runs) > 1 else None
        if tr:
            # the loss saws with each chain's infusion steps: the mean over 8 logged points shows the trend
            loss = np.convolve([h["loss"] for h in tr], np.ones(8) / 8, "valid") if len(tr) >= 16 else \
                [h["loss"] for h in tr]
            ax[0].plot([h["step"] for h in tr][len(tr) - len(loss):], loss, lw=1, label=label)
        key = key or next((k for k in VAL_KEYS if va and k in va[0]), None)
        if key and va:
            ax[1].plot([h["step"] for h in va], [h.get(key, float("nan")) for h in va], "o-", label=label)
    ax[0].set(xlabel="step", ylabel="training loss (mean of 8 logs)", title=f"{title}: loss")
    ax[1].set(xlabel="step", ylabel=key or "validation", title=f"{title}: validation")
    if len(runs) > 1:
        ax[1].legend()
    fig.tight_layout()
    atomic_write(path, lambda f: fig.savefig(f, dpi=80, format="png"))
    plt.close(fig)

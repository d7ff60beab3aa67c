"""MODEL_CARD.md beside the shipped weights, rendered from what the weights files and eval results record,
so the card can never disagree with the weights it describes."""
from __future__ import annotations

import json
import platform
from pathlib import Path

import torch

from hgca_core.io.atomic import atomic_write
from hgca_core.models.weights import WEIGHTS_DIR, load_file

INTRO = """# hgca weights record

What each shipped weights file records of its training, rendered from the files themselves and the eval results
beside them, so this page cannot disagree with the weights it describes. The model card (intended use, training
data, evaluation, limitations) is MODEL_CARD.md at the top of the repository.

Weights trained on procedural street scenes (`hgca_core/synth`), never on real scans. Each file below names its
training data; the three datasets of the completion stages:
- `data/synth` (the first split): two styles, city and suburb; one Waymo-like 64-beam LiDAR with 1 cm point
  noise and 0.02 deg pitch noise; 5 scans per sample. Trained on it last: {synth1}.
- synth2 (generator 6, recipe `docs/data/synth2_recipe.json`, rebuilt by `hgca synth --generator 6`): five sensor
  profiles with their real beam tables and mounting (Velodyne HDL-64E as on KITTI, HDL-32E as on nuScenes, two
  stacked VLP-32C as on Argoverse 2, the Waymo top LiDAR, Ouster OS1-128), 1 to 10 scans per sample, mounting
  height and pitch jitter, random and range-dependent dropout, no return from glass and dark surfaces, range and
  ring-correlated noise, motion distortion, pose noise and drift between scans; sloped, hilly and curved streets,
  more building, vegetation, vehicle and street-furniture types. Trained on it last: {synth2} (each warm-started
  from its first-split weights; see its notes).
- synth2 + synth3 (`--data data/synth2 data/synth3`; synth3 is generator 7, recipe `docs/data/synth3_recipe.json`,
  train seeds from 1,000, so the two share no scene): synth2's sensors and effects, and a fourth street style drawn
  for 30 % of seeds, low-rise commercial strips (single-storey shops of 3.2-5 m, parking lots, open lots behind
  walls, low halls). Validation stays on synth2's val split. Trained on it last: {synth3}.
With the observed free space (cells the input rays crossed) as a further input: {free}. `hgca complete`
computes it from the scans' sensor origins and gives the model an all-unknown grid where a scan has none; by
default (`--free-space auto`) it never outputs a cell in the core of that space (seen-empty cells whose six
neighbours are seen empty too).
Training uses only the train split (seeds 0..999,999; each file below lists the samples it saw); validation
uses seeds 1,000,000+; the evaluations below use the test split (seeds 2,000,000+), which trains nothing.
The shipped weights are the exponential moving average of the training weights where the run kept one, with
BatchNorm's running statistics as the file records them. Stored as fp16, loaded as float32.

Stages: `coarse.pt` (GCA + BEV planner, 20 cm) and `coarse_noplanner.pt` (the ablation) complete the
input's 20 cm occupancy; `fine.pt` (cGCA at 10 cm with the local implicit autoencoder packed inside)
upsamples it into a surface; `autoencoder.pt` is that autoencoder alone, the one `hgca train fine` reads.
A file that is a blend is `(1 - t) * a + t * b` of two trainings, tensor by tensor (WiSE-FT); its section lists
both, and every training run ("session": one stretch of `hgca train`, resumed or not) with its device and steps.

Reading the validation numbers: IoU is at the stage's resolution on fixed val crops of the file's own dataset
(4 for the coarse stage, so they are not comparable between datasets, and noisy: +-0.07 between checks).
The fine stage's and the autoencoder's `val_cd` (metres) is a Chamfer distance to the stored ground-truth surface
samples, of which there is less than one per 10 cm cell: a dense sample of the true surface itself scores
3.9 cm on such crops of the first split, so values near 4 cm sit near that floor.
"""


def _section(path: Path, blob: dict) -> str:
    meta, cfg = blob["meta"], blob.get("config", {})
    dicts = [blob.get("state_dict", {})] + ([blob["autoencoder"]["state_dict"]] if "autoencoder" in blob else [])
    n_params = sum(v.numel() for d in dicts for v in d.values())
    sessions = meta.get("sessions", [])
    lines = [f"## `{path.name}` ({meta.get('stage', meta.get('kind'))})", "",
             f"- file size: {path.stat().st_size / 1e6:.2f} MB, parameters: {n_params:,}",
             f"- architecture: {json.dumps(cfg)}",
             f"- training data: {meta.get('data')} (train split){_samples(meta.get('train_samples'))}"
             + (f", crop {crop} cells" if (crop := meta.get("crop", cfg.get("crop"))) is not None else ""),
             f"- steps: {meta.get('steps')}, summed step wall time: {meta.get('train_wall_s')} s "
             f"over {len(sessions)} session(s)"]
    lines += [_session(s) for s in sessions]
    lines += _origins(meta, "")
    vals = [h for h in meta.get("history_tail", []) if h.get("kind") == "val"]
    trains = [h for h in meta.get("history_tail", []) if h.get("kind") == "train"]
    for note in meta.get("notes", []):
        lines.append(f"- note: {note}")
    if trains:
        lines.append(f"- last logged training loss: {trains[-1]['loss']:.4f} at step {trains[-1]['step']}")
    if vals:
        lines.append("- validation on val-split crops (IoU at the stage's resolution; CD in metres):")
        for h in vals:
            scores = ", ".join(f"{k} {v:.4f}" for k, v in h.items() if k.startswith("val_"))
            lines.append(f"  - step {h['step']}: {scores}")
    return "\n".join(lines)


def _origins(rec: dict, indent: str, listed: str = "") -> list[str]:
    """The weights a record's tensors came from besides its own sessions, nested (`training.export.lineage`): the file
    its run started from and the two files it is a blend of, each with its sessions, so every device and step
    in a file's history is on the card. A start from the file `listed` (by sha256: a blend's a, whose history
    is already on the card) is named, not repeated."""
    lines = []
    init = rec.get("init")
    if init and listed and init.get("sha256") == listed:
        lines.append(f"{indent}- started from {_named(init)}, which is a above")
    elif init:
        lines.append(f"{indent}- started from {_named(init)}: {_trained(init)}")
        lines += [indent + _session(s) for s in init.get("sessions", [])]
        lines += [f"{indent}  - its note: {n}" for n in init.get("notes", [])]
        lines += _origins(init, indent + "  ")
    blend = rec.get("blend")
    if blend:
        a, b = blend["a"], blend["b"]
        lines.append(f"{indent}- blend: these tensors are `(1 - t) * a + t * b`, t = {blend['t']:g} "
                     f"(`hgca_core.training.export.blend_files`, WiSE-FT), a = {_named(a)}, the training above, "
                     f"b = {_named(b)}: {_trained(b)}")
        lines += [indent + _session(s) for s in b.get("sessions", [])]
        lines += [f"{indent}  - note of b: {n}" for n in b.get("notes", [])]
        lines += _origins({"blend": a["blend"]} if "blend" in a else {}, indent + "  ")   # a's start is above
        lines += _origins(b, indent + "  ", listed=str(a.get("sha256", "")))
    return lines


def _named(rec: dict) -> str:
    return f"`{Path(rec['file']).name}` (sha256 {str(rec.get('sha256', ''))[:8]}...)"


def _trained(rec: dict) -> str:
    return (f"{rec.get('steps')} steps, {rec.get('train_wall_s')} s of step wall time on {rec.get('data')} over "
            f"{len(rec.get('sessions', []))} session(s)" + (f", seed {rec['seed']}" if rec.get("seed") else ""))


def _session(s: dict) -> str:
    hardware = s.get("device_name") or s.get("cpu")   # runs before device_name was recorded kept the CPU's
    return (f"  - session ended {s['ended']}: {s['steps']} steps in {s['wall_s']} s, device {s['device']}"
            f"{' (' + hardware + ')' if hardware else ''}, {s['threads']} thread(s), "
            f"world size {s['world_size']}, {s.get('precision', 'fp32')} GEMMs"
            + (f", learning rate {s['lr']:g}" if "lr" in s else "")
            + (f", {s['batch']} chains a step" if "batch" in s else "")   # older records lack it
            + (f", weight average decay {s['ema_decay']:g}" if "ema_decay" in s else "")   # older records lack it
            + "".join(f", {k.replace('_', ' ')} {v}" for k, v in s.get("recipe", {}).items()))


def _samples(names: list[str] | None) -> str:
    """'64 samples, seeds 0-63' from the sample file names a run trained on."""
    if not names:
        return ""
    seeds = sorted(int(n.split("_")[1].split(".")[0]) for n in names)
    return f": {len(seeds)} samples, seeds {seeds[0]}-{seeds[-1]}"


def _by_dataset(blobs: dict[Path, dict]) -> dict[str, str]:
    """The INTRO's file lists, from each file's own metadata (its `data` folder and `free_space` config)."""
    names: dict[str, list[str]] = {"synth1": [], "synth2": [], "synth3": [], "free": []}
    for path, blob in blobs.items():
        data = str(blob["meta"].get("data", ""))
        kind = ("synth3" if "synth3" in data else "synth2" if "synth2" in data
                else "synth1" if data.rstrip("/").endswith("synth") else None)   # other data: its section says
        if kind:
            names[kind].append(f"`{path.name}`")
        if blob.get("config", {}).get("free_space"):
            names["free"].append(f"`{path.name}`")
    return {k: ", ".join(v) or "none of the files here" for k, v in names.items()}


def write_model_card(weights_dir: Path = WEIGHTS_DIR) -> Path:
    blobs = {path: load_file(path) for path in sorted(weights_dir.glob("*.pt"))}   # each file read once
    parts = [INTRO.format(**_by_dataset(blobs)),
             f"Card written with torch {torch.__version__} on {platform.machine()}.", ""]
    for path, blob in blobs.items():
        parts += [_section(path, blob), ""]
    for path in sorted(weights_dir.glob("eval_*.md")):
        parts += [f"## Evaluation: `{path.stem}`", "", path.read_text(), ""]
        js = path.with_suffix(".json")
        info = json.loads(js.read_text()) if js.exists() else {}
        record = "files" in info and "rows" in info   # an `hgca eval` record; other pages (sim_to_real.py) say their own
        if path.with_suffix(".png").exists():   # `hgca eval --render`: the first scene, each row's first completion
            what = ": the first scene" if record or not info else ""
            parts += [f"![{path.stem}{what}]({path.stem}.png)", ""]
        if record:
            data = f"{info['data']}, {info['split']} split" if info.get("data") else f"{info.get('split')} split"
            parts.append(f"Scenes ({data}): {', '.join(info['files'])}; k = {info['samples']} samples; "
                         f"T1 = {info['t1'] or 'default'}; free space {info.get('free_space', 'auto')}.")
            for name, r in info["rows"].items():
                sec = r.get("seconds_per_completion", r.get("seconds_per_scene"))
                origin = f", row from the earlier run `{r['reused_from']}`" if r.get("reused_from") else ""
                parts.append(f"- {name}: {sec:.1f} s per completion (eval process, CPU){origin}")
            parts.append("")
            for note in info.get("notes", []):   # provenance added to the results file by whoever ran it
                parts += [note, ""]
    out = weights_dir / "MODEL_CARD.md"
    atomic_write(out, lambda f: f.write("\n".join(parts).encode()))
    return out

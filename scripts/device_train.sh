#!/usr/bin/env bash
# Train the coarse stage on a lent GPU in one call of the `device` tool (the session's GPU minutes are few: one
# prepared call, no set-up there). The GPU machine has python3 with torch, numpy, scipy, matplotlib and tqdm but
# neither Embree nor trimesh, and sees only this repository plus what `carry` names, 64 MiB in all, so the data
# travels packed (hgca_core/training/packed.py, ~50 kB a scene):
#
#   here:  hgca synth --pack /work/data/synth7f --out gpu_data/synth7f          (gpu_data/ is git-ignored)
#          du -sb gpu_data; git ls-files -z | xargs -0 du -cb | tail -1         (the two under 64 MiB together)
#   there: run(command="bash scripts/device_train.sh", carry=["gpu_data"], timeout_s=600)
#
# More scenes than one call carries (64 MiB with the repository): the machine stays warm 30 s after a call and keeps
# what a call wrote outside the repository, so the first calls move one batch of packed folders each aside and the
# training call, right after them, carries the last batch and trains on all. Each batch in its own git-ignored folder
# here (gpu_data, gpu_data_b, ...; folder names inside them all different), named by PACKED:
#   run(command="STASH_ONLY=1 bash scripts/device_train.sh", carry=["gpu_data"])                  # -> $STASH
#   run(command="STASH_ONLY=1 PACKED=gpu_data_b bash scripts/device_train.sh", carry=["gpu_data_b"])
#   run(command="PACKED=gpu_data_c bash scripts/device_train.sh", carry=["gpu_data_c"], timeout_s=600)
#
# Several runs share the one GPU in a call (three bf16 runs at batch 6 kept an H200 99 % busy with 2 GB each in
# session 27): VARIANTS="e:DISTILL=1,CUT_FREE=1 n:DISTILL=1 p" trains three side by side, each `name` or
# `name:KEY=V,...` with KEY one of the settings below; the default is one run named coarse_gpu. What comes back in
# $OUT, two files a run (the device tool returns at most 8 files, so at most 3 runs): <name>.pt (the EMA weights
# with their training record: continue with `hgca train coarse --init-from`, compare with benchmarks/val_cut.py
# and `hgca eval-real`) and <name>.history.json, beside device_train.log (every run's lines, prefixed [name]) and
# curves.png. Settings by environment, for every run unless its variant overrides them: DATA (packed folders,
# space-separated; default every folder in gpu_data/ and $STASH, those with a val split first: validation reads the
# first one's, which may hold the val split alone), MINUTES (training budget, default 7), BATCH (chains per step,
# default 6, the paper's), LR, INIT (weights to start from), TURN (share of inputs turned by a random yaw, default 0),
# FROZEN=1 (--frozen-bn: BatchNorm keeps INIT's running statistics), CUT_FREE=1 (--cut-free-loss: the free-space weight
# also on what a cut input's uncut scan saw empty), DISTILL=MU (--distill: cut inputs' targets move MU of the way to the
# probabilities of TEACHER, default INIT), ABOVE=1 (--distill-above: only the cells at and above the cut move), SEED (a
# new run's --seed, default 0: VARIANTS="s0:SEED=0 s1:SEED=1 s2:SEED=2" trains three seeds of one recipe side by side,
# whose spread `benchmarks/run_spread.py` measures); and for
# the call: RESUME=1 (a later call on the still-warm machine continues each VARIANTS name's run of an earlier call
# from its checkpoint in RUN, for MINUTES more, keeping the run's recipe, lr and teacher, and saying which of a
# variant's settings other than MINUTES and BATCH it ignores; carry the same data),
# DEVICE (default cuda; cpu runs the same path here, as tests/test_device_script.py does), THREADS (CPU
# threads a run, default the cores shared out), RUN (the runs' checkpoint folders, default /tmp/hgca_device_run/<name>),
# STASH (where STASH_ONLY=1 puts the folders of PACKED, default gpu_data, and where the default DATA looks too, default
# /tmp/hgca_stash).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:?set OUT to the folder that comes back}
DEVICE=${DEVICE:-cuda}
MINUTES=${MINUTES:-7}
BATCH=${BATCH:-6}
LR=${LR:-1.5e-4}
TURN=${TURN:-0}
INIT=${INIT:-hgca_core/weights/coarse.pt}
PACKED=${PACKED:-gpu_data}
STASH=${STASH:-/tmp/hgca_stash}
fail() { echo "device_train: $*" >&2; exit 2; }
if [ "${STASH_ONLY:-0}" = 1 ]; then  # the first of two calls: set this batch aside for the training call
  mkdir -p "$STASH"
  for d in "$PACKED"/*/; do
    [ -d "$d" ] || fail "no packed data in $PACKED/ to set aside"
    [ ! -e "$STASH/$(basename "$d")" ] || fail "$STASH/$(basename "$d") exists already: name each batch's folders apart"
    cp -r "$d" "$STASH/"
  done
  echo "set aside in $STASH:"; du -sh "$STASH"/*; exit 0
fi
if [ -z "${DATA:-}" ]; then  # every packed folder, those with a val split first (validation reads the first's)
  ALL=$(find "$PACKED" "$STASH" -mindepth 1 -maxdepth 1 -type d 2>/dev/null | sort)
  DATA=$(for d in $ALL; do [ -d "$d/val" ] && echo "$d"; done; for d in $ALL; do [ -d "$d/val" ] || echo "$d"; done)
  DATA=$(echo $DATA)
fi
VARIANTS=${VARIANTS:-coarse_gpu}
PY=${PY:-python3}
RUN=${RUN:-/tmp/hgca_device_run}
KEYS=" MINUTES BATCH LR TURN INIT FROZEN CUT_FREE DISTILL TEACHER ABOVE SEED "
[ -n "${DATA// /}" ] || fail "no packed data: pack a dataset into gpu_data/<name> and carry gpu_data"
read -r -a RUNS <<< "$VARIANTS"
[ "${#RUNS[@]}" -le 3 ] || fail "VARIANTS names ${#RUNS[@]} runs; at most 3 fit the device tool's 8 returned files"
settings() { [[ $1 != *:* ]] || tr , '\n' <<< "${1#*:}"; }  # a variant's KEY=V items, one a line
NAMES=()
for v in "${RUNS[@]}"; do
  name=${v%%:*}
  if ! [[ $name =~ ^[A-Za-z0-9_-]+$ ]] || [[ " ${NAMES[*]-} " == *" $name "* ]]; then
    fail "variant name '$name' in VARIANTS is empty, repeated or not made of letters, digits, _ and -"
  fi
  mapfile -t kv < <(settings "$v")
  for a in ${kv[@]+"${kv[@]}"}; do
    [[ $a == *=* && $KEYS == *" ${a%%=*} "* ]] || fail "'$a' in variant '$name': expected KEY=V, KEY one of$KEYS"
  done
  NAMES+=("$name")
done
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
SHARE=$(( $(nproc) / ${#RUNS[@]} ))
export OMP_NUM_THREADS=${THREADS:-$(( SHARE > 0 ? SHARE : 1 ))}
mkdir -p "$OUT"

train_one() {  # one variant; called in a subshell, so its settings stay its own
  local name=${1%%:*} a kv flags=()
  mapfile -t kv < <(settings "$1")
  for a in ${kv[@]+"${kv[@]}"}; do export "${a%%=*}=${a#*=}"; done
  [ "${FROZEN:-0}" = 1 ] && flags+=(--frozen-bn)
  [ "${CUT_FREE:-0}" = 1 ] && flags+=(--cut-free-loss)
  [ "${DISTILL:-0}" != 0 ] && flags+=(--distill "$DISTILL")
  [ -n "${TEACHER:-}" ] && flags+=(--teacher "$TEACHER")
  [ "${ABOVE:-0}" = 1 ] && flags+=(--distill-above)
  local start=(--init-from "$INIT" --free-space --free-weight 8 --cut 0.5 --focus 0.5 --lr "$LR" --turn "$TURN"
               --seed "${SEED:-0}")
  if [ "${RESUME:-0}" = 1 ]; then  # the run of an earlier call on this warm machine, with the recipe it had
    [ -f "$RUN/$name/ckpt.pt" ] || { echo "[$name] RESUME=1 but no $RUN/$name/ckpt.pt: the machine was given back"\
      "(or another VARIANTS name); start it without RESUME" >&2; return 2; }
    start=(--resume) flags=()
    for a in ${kv[@]+"${kv[@]}"}; do  # only the budget and the batch are the call's; the rest is the run's own
      case ${a%%=*} in MINUTES|BATCH) ;; *) echo "[$name] RESUME=1 keeps the run's recipe: $a ignored" >&2 ;; esac
    done
  fi
  mkdir -p "$RUN/$name"
  # shellcheck disable=SC2086  # DATA is a list of folders
  "$PY" -m hgca_core.cli train coarse --data $DATA --out "$RUN/$name" --device "$DEVICE" --batch "$BATCH" \
    --minutes "$MINUTES" "${start[@]}" --precision bf16 --val-every "$MINUTES" --no-progress \
    --export "$OUT/$name.pt" ${flags[@]+"${flags[@]}"} 2>&1 | sed -u "s/^/[$name] /"
  return "${PIPESTATUS[0]}"
}

{
  echo "data: $DATA"
  echo "runs: ${RUNS[*]} ($OMP_NUM_THREADS CPU threads each)"
  "$PY" - "$DEVICE" <<'EOF'
import sys, torch, numpy
dev = sys.argv[1]
print("torch", torch.__version__, "numpy", numpy.__version__, "cuda", torch.version.cuda)
if dev.startswith("cuda"):
    print("gpu", torch.cuda.get_device_name(0), "bf16", torch.cuda.is_bf16_supported())
EOF
  pids=()
  for v in "${RUNS[@]}"; do ( train_one "$v" ) & pids+=($!); done
  rc=0
  for p in "${pids[@]}"; do wait "$p" || rc=$?; done
  "$PY" - "$RUN" "$OUT" "$DEVICE" "${NAMES[@]}" <<'EOF'
import json, sys
from pathlib import Path
import torch
from hgca_core.training.trainer import plot_histories
run, out, device, names = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3], sys.argv[4:]
runs = {}
for name in names:
    ck = run / name / "ckpt.pt"
    if not ck.exists():
        print(f"[{name}] no checkpoint: the run failed before its first save")
        continue
    st = torch.load(ck, map_location="cpu", weights_only=True)["state"]
    record = {"step": st["step"], "elapsed_s": st["elapsed_s"], "sessions": st["sessions"], "history": st["history"]}
    (out / f"{name}.history.json").write_text(json.dumps(record, indent=1))
    runs[name] = st["history"]
    steps = [h["step_s"] for h in st["history"] if h.get("kind") == "train" and "step_s" in h]
    print(f"[{name}] steps {st['step']}, step time (mean of 10-step means) {sum(steps) / max(len(steps), 1):.3f} s")
if runs:
    where = torch.cuda.get_device_name(0) if device.startswith("cuda") else "cpu"
    plot_histories(runs, out / "curves.png", f"coarse, {where}")
EOF
  exit "$rc"
} 2>&1 | tee "$OUT/device_train.log"
exit "${PIPESTATUS[0]}"

#!/usr/bin/env bash
# Train the coarse stage on a lent GPU in one call of the `device` tool (the session's GPU minutes are few: one
# prepared call, no set-up there). The GPU machine has python3 with torch, numpy, scipy, matplotlib and tqdm but
# neither Embree nor trimesh, and sees only this repository plus what `carry` names, 64 MiB in all, so the data
# travels packed (hgca_core/training/packed.py, ~60 kB a scene):
#
#   here:  hgca synth --pack /work/data/synth7f --out gpu_data/synth7f          (gpu_data/ is git-ignored)
#          du -sh gpu_data; git ls-files -z | xargs -0 du -cb | tail -1          (the two under 64 MiB together)
#   there: run(command="bash scripts/device_train.sh", carry=["gpu_data"], timeout_s=600)
#
# What comes back in $OUT: coarse_gpu.pt (the EMA weights with their training record: continue with
# `hgca train coarse --init-from`, compare with benchmarks/val_cut.py and `hgca eval-real`), curve.png, the
# run's history (history.json) and the log. Settings by environment: DATA (packed folders, space-separated;
# default every folder in gpu_data/, validation on the first one's val split), MINUTES (training budget,
# default 7), BATCH (chains per step, default 6, the paper's), LR, INIT (weights to start from), TURN (share of
# inputs turned by a random yaw, default 0), FROZEN=1 (--frozen-bn: BatchNorm keeps INIT's running statistics),
# CUT_FREE=1 (--cut-free-loss: the free-space weight also on what a cut input's uncut scan saw empty), DISTILL=MU
# (--distill: cut inputs' targets move MU of the way to the probabilities of TEACHER, default INIT), ABOVE=1
# (--distill-above: only the cells at and above the cut move), DEVICE
# (default cuda; cpu runs the same path here, as tests/test_device_script.py does).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:?set OUT to the folder that comes back}
DEVICE=${DEVICE:-cuda}
MINUTES=${MINUTES:-7}
BATCH=${BATCH:-6}
LR=${LR:-1.5e-4}
TURN=${TURN:-0}
INIT=${INIT:-hgca_core/weights/coarse.pt}
DATA=${DATA:-$(find gpu_data -mindepth 1 -maxdepth 1 -type d 2>/dev/null | sort | tr '\n' ' ')}
FLAGS=()
[ "${FROZEN:-0}" = 1 ] && FLAGS+=(--frozen-bn)
[ "${CUT_FREE:-0}" = 1 ] && FLAGS+=(--cut-free-loss)
[ "${DISTILL:-0}" != 0 ] && FLAGS+=(--distill "$DISTILL")
[ -n "${TEACHER:-}" ] && FLAGS+=(--teacher "$TEACHER")
[ "${ABOVE:-0}" = 1 ] && FLAGS+=(--distill-above)
PY=${PY:-python3}
RUN=${RUN:-/tmp/hgca_device_run}
if [ -z "${DATA// /}" ]; then
  echo "device_train: no packed data: pack a dataset into gpu_data/<name> and carry gpu_data" >&2
  exit 2
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
mkdir -p "$OUT" "$RUN"
{
  echo "data: $DATA"
  "$PY" - "$DEVICE" <<'EOF'
import sys, torch, numpy
dev = sys.argv[1]
print("torch", torch.__version__, "numpy", numpy.__version__, "cuda", torch.version.cuda)
if dev.startswith("cuda"):
    print("gpu", torch.cuda.get_device_name(0), "bf16", torch.cuda.is_bf16_supported())
EOF
  # shellcheck disable=SC2086  # DATA is a list of folders
  "$PY" -m hgca_core.cli train coarse --data $DATA --out "$RUN" --device "$DEVICE" --batch "$BATCH" \
    --minutes "$MINUTES" --init-from "$INIT" --free-space --free-weight 8 --cut 0.5 --focus 0.5 --lr "$LR" \
    --turn "$TURN" --precision bf16 --val-every "$MINUTES" --no-progress --export "$OUT/coarse_gpu.pt" ${FLAGS[@]+"${FLAGS[@]}"}
} 2>&1 | tee "$OUT/device_train.log"
cp "$RUN/curve.png" "$OUT/" 2>/dev/null || true
"$PY" - "$RUN/ckpt.pt" "$OUT/history.json" <<'EOF'
import json, sys, torch
ck = torch.load(sys.argv[1], map_location="cpu", weights_only=True)
st = ck["state"]
json.dump({"step": st["step"], "elapsed_s": st["elapsed_s"], "sessions": st["sessions"],
           "history": st["history"]}, open(sys.argv[2], "w"), indent=1)
steps = [h["step_s"] for h in st["history"] if h.get("kind") == "train" and "step_s" in h]
print(f"steps {st['step']}, step time (mean of 10-step means) {sum(steps) / max(len(steps), 1):.3f} s")
EOF

#!/usr/bin/env bash
# The prepared GPU check, from the repository root of a machine with a CUDA GPU, in under 5 minutes:
#   scripts/gpu_check.sh [benchmarks/gpu_check.py options, e.g. --out DIR]
# It needs gpu_data/ (`benchmarks/gpu_check.py --prepare gpu_data`, made where the project's dependencies are)
# and, where that machine's Python lacks the project's pure mesh packages, their wheels in .whl/
# (scripts/gpu_wheels.sh). It installs nothing else, except torch==2.13.0 (the project's pin) where the
# Python's own torch sees no GPU.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if compgen -G ".whl/*.whl" > /dev/null; then
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/hgca_site .whl/*.whl
  export PYTHONPATH=/tmp/hgca_site
fi
if ! "$PY" -c "import sys, torch; sys.exit(not torch.cuda.is_available())" 2>/dev/null; then
  echo "gpu_check.sh: this Python's torch sees no CUDA GPU; installing torch==2.13.0" >&2
  "$PY" -m pip install -q torch==2.13.0
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null || true
exec "$PY" benchmarks/gpu_check.py --device "${HGCA_DEVICE:-cuda}" "$@"

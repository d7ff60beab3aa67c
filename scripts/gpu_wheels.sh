#!/usr/bin/env bash
# Wheels (CPython 3.12, x86-64 Linux) of the packages hgca's completion needs that a GPU image may lack, into
# .whl/ (git-ignored) for scripts/gpu_check.sh to install there: the versions this checkout's .venv holds.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d .whl \
  trimesh==5.2.0 fast_simplification==0.2.0 pykdtree==1.4.3 plyfile==1.1.3
ls -l .whl

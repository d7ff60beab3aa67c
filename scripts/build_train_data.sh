#!/usr/bin/env bash
# Rebuild the scenes the shipped coarse weights were trained, validated and tested on, on any machine (the data is
# not in the repository: these commands regenerate it bit for bit from seeds). The folders, by name (DATA, default
# data/), each a resumable `hgca synth` split build (re-running skips the scenes already written), in the order a
# training run needs them:
#   v2f        the 16 val scenes of synth2f alone (generator 6, val seeds 1,000,000-15): the trainer's validation
#              (a first --data folder holding only a val split) and the 16-scene val set
#   synth2cal  val seeds 16-63 (generator 6): further val scenes
#   synth2f    the 8 format-3 test scenes (generator 6, test seeds 2,000,000-7): `hgca eval --split test`
#   s6a..s6d   generator 6 train seeds 0-339, 340-679, 680-1,019, 1,020-1,359 (340 each)
#   s7a        generator 7 train seeds 1,500-1,670 (171)
# The 1,531 train scenes of s6a-s6d and s7a are the train set the shipped coarse.pt's last fine-tune saw (its card,
# `generator 6 seeds 0-1,359 and generator 7 seeds 1,500-1,670`); recipes docs/data/synth2f_recipe.json (generator 6,
# format 3) and synth7f_recipe.json (generator 7). With two workers on a 2-core AMD EPYC: s7a's 171
# scenes in 13 min (4.7 s a scene), s6a's 340 in 32 min and v2f + synth2cal in 8.5 min, those partly beside a scoring run.
#
#   bash scripts/build_train_data.sh                    # everything (1,603 scenes), ~2 h on 2 cores
#   FOLDERS="v2f synth2cal s6a s7a" bash scripts/build_train_data.sh
#   DRY_RUN=1 bash scripts/build_train_data.sh          # print the commands only
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${DATA:-data}
WORKERS=${WORKERS:-2}
KNOWN="v2f synth2cal synth2f s6a s6b s6c s6d s7a"   # the case below, in build order
FOLDERS=${FOLDERS:-$KNOWN}
HGCA=${HGCA:-.venv/bin/hgca}

args_for() {
  case "$1" in
    v2f) echo "--split val --count 16 --generator 6" ;;
    synth2cal) echo "--split val --first 16 --count 48 --generator 6" ;;
    synth2f) echo "--split test --count 8 --generator 6" ;;
    s6a) echo "--split train --first 0 --count 340 --generator 6" ;;
    s6b) echo "--split train --first 340 --count 340 --generator 6" ;;
    s6c) echo "--split train --first 680 --count 340 --generator 6" ;;
    s6d) echo "--split train --first 1020 --count 340 --generator 6" ;;
    s7a) echo "--split train --first 1500 --count 171 --generator 7" ;;
    *) echo "build_train_data.sh: unknown folder '$1' (known: $KNOWN)" >&2; return 2 ;;
  esac
}

for f in $FOLDERS; do
  a=$(args_for "$f")
  cmd="$HGCA synth $a --workers $WORKERS --out $DATA/$f"
  if [ -n "${DRY_RUN:-}" ]; then echo "$cmd"; continue; fi
  echo "[$(date -u +%H:%M:%S)] $cmd"
  $cmd
done

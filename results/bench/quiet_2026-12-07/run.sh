#!/usr/bin/env bash
# Issue 35, on a quiet machine (nothing else running): the baseline 828260c (a worktree at
# $BASE) and this checkout, one process at a time, float32 and run.precision=bf16.
# Usage: results/bench/quiet_2026-12-07/run.sh /path/to/worktree-of-828260c
set -euo pipefail
BASE=$1
OUT=results/bench/quiet_2026-12-07
PY=${PY:-.venv/bin/python}
lscpu | grep -E "Model name" > $OUT/machine.txt
grep -o -w "amx_bf16\|avx512_bf16" /proc/cpuinfo | sort -u >> $OUT/machine.txt
load() { echo "$1 $(date -u +%H:%M:%S) $(cut -d' ' -f1-3 /proc/loadavg)" >> $OUT/load.txt; }
learn="bench learn --env skirmish/3m --algo qmix --target-win 0.95 --seeds 3"
load base_learn; (cd "$BASE" && PYTHONPATH=. "$OLDPWD/$PY" -m cluster.cli $learn) > $OUT/learn_3m_qmix_base.json
load new_learn; PYTHONPATH=. $PY -m cluster.cli $learn --out $OUT/learn_3m_qmix_f32.json > /dev/null
load new_learn_bf16; PYTHONPATH=. $PY -m cluster.cli $learn --set run.precision=bf16 --out $OUT/learn_3m_qmix_bf16.json > /dev/null
for algo in rdn vdn qmix; do
  train="bench train --env skirmish/bane_vs_bane --algo $algo --seeds 3 --steps 2000"
  load "train_$algo"; PYTHONPATH=. $PY -m cluster.cli $train --out $OUT/train_bvb_${algo}_f32.json > /dev/null
  load "train_${algo}_bf16"; PYTHONPATH=. $PY -m cluster.cli $train --set run.precision=bf16 --out $OUT/train_bvb_${algo}_bf16.json > /dev/null
done
load end

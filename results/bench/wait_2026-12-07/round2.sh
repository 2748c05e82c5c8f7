#!/usr/bin/env bash
# A second round of run.sh's auto-thread cases (the candidate default: PASSIVE with
# GOMP_SPINCOUNT=10000 against the shipped PASSIVE), in the opposite order, nothing else running.
# Usage, from the repository root: results/bench/wait_2026-12-07/round2.sh
set -euo pipefail
OUT=results/bench/wait_2026-12-07
PY=${PY:-.venv/bin/python}
load() { echo "$1 $(date -u +%H:%M:%S) $(cut -d' ' -f1-3 /proc/loadavg)" >> $OUT/load.txt; }
learn="bench learn --env skirmish/3m --algo qmix --target-win 0.95 --seeds 3 --compare-load --threads 0"
train="bench train --env skirmish/bane_vs_bane --algo rdn --seeds 3 --steps 1500 --set run.torch_threads=0"
for wait in spin10k passive; do
  spin=(); [ $wait = spin10k ] && spin=(GOMP_SPINCOUNT=10000)
  load "round2_learn_${wait}_t0"
  env -u GOMP_SPINCOUNT OMP_WAIT_POLICY=PASSIVE "${spin[@]}" PYTHONPATH=. $PY -m cluster.cli $learn \
    --out $OUT/learn_3m_qmix_${wait}_t0_round2.json > /dev/null
  load "round2_train_${wait}_quiet"
  env -u GOMP_SPINCOUNT OMP_WAIT_POLICY=PASSIVE "${spin[@]}" PYTHONPATH=. $PY -m cluster.cli $train \
    --out $OUT/train_bvb_rdn_${wait}_quiet_round2.json > /dev/null
  PYTHONPATH=. $PY -m cluster.cli bench load --seconds 900 > /dev/null & busy=$!
  sleep 5; load "round2_train_${wait}_loaded"
  env -u GOMP_SPINCOUNT OMP_WAIT_POLICY=PASSIVE "${spin[@]}" PYTHONPATH=. $PY -m cluster.cli $train \
    --out $OUT/train_bvb_rdn_${wait}_loaded_round2.json > /dev/null
  pkill -TERM -P $busy 2>/dev/null || true; kill $busy 2>/dev/null || true; wait $busy 2>/dev/null || true
done
load round2_end

#!/usr/bin/env bash
# Issue 35 items 4 and the 3m learning target: bench learn's default thread count. With the
# shipped OMP_WAIT_POLICY=PASSIVE, is "auto" (two threads on a quiet 2-core machine) or one
# thread faster, quiet and beside `credit bench load` (--compare-load)? Two rounds, the order
# swapped in the second, nothing else running. Usage, from the repository root:
#   results/bench/threads_2026-12-07/run.sh
set -euo pipefail
OUT=results/bench/threads_2026-12-07
PY=${PY:-.venv/bin/python}
lscpu | grep -E "Model name" > $OUT/machine.txt
grep -o -w "amx_bf16\|avx512_bf16" /proc/cpuinfo | sort -u >> $OUT/machine.txt
git rev-parse HEAD >> $OUT/machine.txt
load() { echo "$1 $(date -u +%H:%M:%S) $(cut -d' ' -f1-3 /proc/loadavg)" >> $OUT/load.txt; }
learn="bench learn --env skirmish/3m --algo qmix --target-win 0.95 --seeds 3 --compare-load"
for round in 1 2; do
  order="1 0"; [ $round = 2 ] && order="0 1"
  for threads in $order; do
    load "round${round}_t${threads}"
    PYTHONPATH=. $PY -m cluster.cli $learn --threads $threads \
      --out $OUT/learn_3m_qmix_t${threads}_round${round}.json > /dev/null
  done
done
load end

#!/usr/bin/env bash
# After run_threads.sh, same machine: quiet and beside `credit bench load` (one busy process
# per CPU), the shipped wait (PASSIVE) against libgomp's default policy with a short spin
# (the candidate of wait_39138e3/), both with the auto thread count.
set -euo pipefail
OUT=results/bench/quiet_2026-12-07
PY=${PY:-.venv/bin/python}
load() { echo "$1 $(date -u +%H:%M:%S) $(cut -d' ' -f1-3 /proc/loadavg)" >> $OUT/load.txt; }
learn="bench learn --env skirmish/3m --algo qmix --target-win 0.95 --seeds 3 --compare-load"
load shipped_compare_load; PYTHONPATH=. $PY -m cluster.cli $learn --out $OUT/learn_3m_qmix_compare_load.json > /dev/null
load spin_compare_load; OMP_WAIT_POLICY= GOMP_SPINCOUNT=10000 PYTHONPATH=. $PY -m cluster.cli $learn --out $OUT/learn_3m_qmix_compare_load_spin10k.json > /dev/null 2> $OUT/spin_stderr.txt
load end3

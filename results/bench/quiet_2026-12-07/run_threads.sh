#!/usr/bin/env bash
# After run.sh, same quiet machine: is the 3m slowdown against 828260c the thread count or
# OpenMP's wait policy? Two threads with spinning threads (OMP_WAIT_POLICY=ACTIVE, what
# 828260c ran with), and one thread (PASSIVE, the shipped default).
set -euo pipefail
OUT=results/bench/quiet_2026-12-07
PY=${PY:-.venv/bin/python}
load() { echo "$1 $(date -u +%H:%M:%S) $(cut -d' ' -f1-3 /proc/loadavg)" >> $OUT/load.txt; }
learn="bench learn --env skirmish/3m --algo qmix --target-win 0.95 --seeds 3"
load new_learn_active; OMP_WAIT_POLICY=ACTIVE PYTHONPATH=. $PY -m cluster.cli $learn --out $OUT/learn_3m_qmix_f32_active.json > /dev/null
load new_learn_threads1; PYTHONPATH=. $PY -m cluster.cli $learn --threads 1 --out $OUT/learn_3m_qmix_f32_threads1.json > /dev/null
load new_learn_again; PYTHONPATH=. $PY -m cluster.cli $learn --out $OUT/learn_3m_qmix_f32_again.json > /dev/null
load end2

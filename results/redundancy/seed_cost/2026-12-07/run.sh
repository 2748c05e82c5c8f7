#!/bin/bash
# Cost probes of one seed on bane_vs_bane, bane_z24 and bane_z30 (results/redundancy/NOTES.md,
# "What a map above 20 zerglings costs"): the real training loop's first 6k env steps of one
# seed, one thread, from a worktree of the table's commit (30465cf; T52=that worktree, VENV=a
# venv with credit's dependencies), two probes at once (one per core). Writes JSON here.
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
cd "${T52:?worktree of 30465cf}"
probe() {  # env algo
  PYTHONPATH=. "${VENV:?venv}"/bin/python -m cluster.cli bench train --env skirmish/$1 --algo $2 \
    --seeds 1 --steps 6000 --test-interval 100000 --set run.torch_threads=1 \
    --out "$HERE/$1_$2_threads1.json" > "$HERE/$1_$2.log" 2>&1
}
# bane_vs_bane beside bane_z30, one algorithm at a time
for algo in qmix_ns iql rdn vdn qmix; do
  uptime >> "$HERE/load.txt"
  probe bane_vs_bane $algo & probe bane_z30 $algo & wait
done
# then bane_z24, two algorithms at a time
for pair in "qmix_ns rdn" "iql vdn"; do
  set -- $pair
  uptime >> "$HERE/load.txt"
  probe bane_z24 $1 & probe bane_z24 $2 & wait
done
uptime >> "$HERE/load.txt"

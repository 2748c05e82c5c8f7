#!/bin/bash
# The seeds that will run alone on the machine (IQL on bane_med and bane_z21, QMIX-nostate with
# the like-for-like recipe on bane_vs_bane): the same 6k-env-step probe as run.sh, one at a
# time with nothing else running, on one thread and on two spinning threads
# (OMP_WAIT_POLICY=ACTIVE, run.torch_threads=2), as ../2026-12-07/alone/ did for bane_vs_bane.
# T52=worktree of 30465cf, VENV=a venv with credit's dependencies. Writes JSON in alone/.
set -u
HERE=$(cd "$(dirname "$0")" && pwd)/alone
cd "${T52:?worktree of 30465cf}"
probe() {  # env algo threads wait [--set ...]
  local name="$1_$2${5:+_gru_one_step}_threads$3${4:+_active}"
  echo "$name $(date -u +%H:%M:%S) $(cut -d' ' -f1-3 /proc/loadavg)" >> "$HERE/load.txt"
  env ${4:+OMP_WAIT_POLICY=ACTIVE} PYTHONPATH=. "${VENV:?venv}"/bin/python -m cluster.cli bench \
    train --env skirmish/$1 --algo $2 --seeds 1 --steps 6000 --test-interval 100000 \
    --set run.torch_threads=$3 "${@:5}" --out "$HERE/$name.json" > /dev/null
}
for spec in "bane_med iql" "bane_z21 iql" "bane_vs_bane qmix_ns --set recipe=gru_one_step"; do
  set -- $spec
  probe $1 $2 1 "" "${@:3}"
  probe $1 $2 2 active "${@:3}"
done
echo "end $(date -u +%H:%M:%S) $(cut -d' ' -f1-3 /proc/loadavg)" >> "$HERE/load.txt"

#!/bin/bash
# Cost probes of one seed on bane_z21 (the candidate for Table 5.1's map above 20 zerglings:
# the nearest to 20) and of bane_med's four algorithms (results/redundancy/NOTES.md): the real
# training loop's first 6k env steps of one seed, one thread, from a worktree of the table's
# commit (30465cf; T52=that worktree, VENV=a venv with credit's dependencies). The same probe as
# ../2026-12-07/run.sh, whose bane_vs_bane probes are the reference. Two lists, each run one
# probe after another, side by side (one per core):
#   run.sh z21 & run.sh med & wait
# and then, alone on the machine, `run.sh ref`. Writes JSON here.
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
cd "${T52:?worktree of 30465cf}"
probe() {  # env algo [tag [--set ...]]
  local name="$1_$2_threads1${3:+_$3}"
  echo "$name $(date -u +%H:%M:%S) $(cut -d' ' -f1-3 /proc/loadavg)" >> "$HERE/load.txt"
  PYTHONPATH=. "${VENV:?venv}"/bin/python -m cluster.cli bench train --env skirmish/$1 --algo $2 \
    --seeds 1 --steps 6000 --test-interval 100000 --set run.torch_threads=1 "${@:4}" \
    --out "$HERE/$name.json" > /dev/null
}
case ${1:?z21, med or ref} in
  z21) for algo in qmix_ns iql rdn vdn qmix; do probe bane_z21 $algo; done ;;
  med) for algo in qmix_ns rdn iql vdn; do probe bane_med $algo; done ;;
  # then, the same window, bane_vs_bane beside bane_z21 one algorithm at a time (the ratio
  # between sessions drifted), and the like-for-like QMIX and QMIX-nostate on bane_vs_bane
  ref)
    for algo in rdn qmix_ns iql vdn; do probe bane_vs_bane $algo & probe bane_z21 $algo again & wait; done
    for algo in qmix qmix_ns; do probe bane_vs_bane $algo gru_one_step --set recipe=gru_one_step & done
    wait ;;
esac
echo "end $1 $(date -u +%H:%M:%S) $(cut -d' ' -f1-3 /proc/loadavg)" >> "$HERE/load.txt"

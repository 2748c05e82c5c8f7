#!/usr/bin/env bash
# Issue 35 item 4: how long torch's OpenMP threads spin before they sleep, on a machine with
# nothing else running. Three waits: the shipped OMP_WAIT_POLICY=PASSIVE (no spin), and
# PASSIVE with GOMP_SPINCOUNT=1000 and =10000 spins before a sleeping wait.
# Each with the auto thread count (bench learn's default) and with --threads 2 fixed, each
# quiet and beside `credit bench load` (--compare-load: one busy process per CPU); then the
# training loop on bane_vs_bane (RDN, 3 seeds, auto threads) quiet and beside the load.
# Usage, from the repository root: results/bench/wait_2026-12-07/run.sh [learn|train|all]
set -euo pipefail
OUT=results/bench/wait_2026-12-07
PY=${PY:-.venv/bin/python}
lscpu | grep -E "Model name" > $OUT/machine.txt
grep -o -w "amx_bf16\|avx512_bf16" /proc/cpuinfo | sort -u >> $OUT/machine.txt
git rev-parse HEAD >> $OUT/machine.txt
load() { echo "$1 $(date -u +%H:%M:%S) $(cut -d' ' -f1-3 /proc/loadavg)" >> $OUT/load.txt; }
# wait NAME -> the environment for it: PASSIVE with no spin (credit's shipped setting), or
# PASSIVE with GOMP_SPINCOUNT spins first (libgomp takes GOMP_SPINCOUNT as the spin before
# a thread sleeps whatever the policy; PASSIVE only sets the default spin to 0)
with_wait() {
  case $1 in
    passive) env -u GOMP_SPINCOUNT OMP_WAIT_POLICY=PASSIVE "${@:2}" ;;
    spin1k) env OMP_WAIT_POLICY=PASSIVE GOMP_SPINCOUNT=1000 "${@:2}" ;;
    spin10k) env OMP_WAIT_POLICY=PASSIVE GOMP_SPINCOUNT=10000 "${@:2}" ;;
  esac
}
learn="bench learn --env skirmish/3m --algo qmix --target-win 0.95 --seeds 3 --compare-load"
[ "${1:-all}" = train ] || for wait in passive spin1k spin10k; do
  for threads in 0 2; do
    load "learn_${wait}_t${threads}"
    with_wait $wait env PYTHONPATH=. $PY -m cluster.cli $learn --threads $threads \
      --out $OUT/learn_3m_qmix_${wait}_t${threads}.json > /dev/null
  done
done
[ "${1:-all}" = learn ] && { load end; exit 0; }
train="bench train --env skirmish/bane_vs_bane --algo rdn --seeds 3 --steps 1500 --set run.torch_threads=0"
for wait in passive spin10k spin1k; do
  load "train_${wait}_quiet"
  with_wait $wait env PYTHONPATH=. $PY -m cluster.cli $train --out $OUT/train_bvb_rdn_${wait}_quiet.json > /dev/null
  PYTHONPATH=. $PY -m cluster.cli bench load --seconds 900 > /dev/null & busy=$!
  sleep 5; load "train_${wait}_loaded"
  with_wait $wait env PYTHONPATH=. $PY -m cluster.cli $train --out $OUT/train_bvb_rdn_${wait}_loaded.json > /dev/null
  pkill -TERM -P $busy 2>/dev/null || true; kill $busy 2>/dev/null || true; wait $busy 2>/dev/null || true
done
load end

#!/usr/bin/env bash
# The shipped OpenMP wait before and after 4a22a00 (PASSIVE -> PASSIVE with GOMP_SPINCOUNT=10000),
# side by side on one machine with nothing else running: each tree with its own default (the
# two variables unset in the environment), PYTHONPATH at the tree, the same venv.
#   OLD: a worktree of ddef8c1 (the default before), NEW: this checkout, BASE: a worktree of
#   828260c (issue 35's baseline; its bench learn has no --compare-load).
# Usage, from the repository root:
#   OLD=../wt/old BASE=../wt/base results/bench/spin_default_2026-12-07/run.sh [round1|round2|fixed|base]...
set -euo pipefail
OUT=results/bench/spin_default_2026-12-07
PY=${PY:-$PWD/.venv/bin/python}  # not resolved: the symlink is what makes it the venv
NEW=$(pwd)
lscpu | grep -E "Model name" > $OUT/machine.txt
grep -o -w "amx_bf16\|avx512_bf16" /proc/cpuinfo | sort -u >> $OUT/machine.txt
echo "new $(git rev-parse HEAD) old $(git -C $OLD rev-parse HEAD) base $(git -C $BASE rev-parse HEAD)" >> $OUT/machine.txt
load() { echo "$1 $(date -u +%H:%M:%S) $(cut -d' ' -f1-3 /proc/loadavg)" >> $OUT/load.txt; }
credit() { (cd $1 && env -u OMP_WAIT_POLICY -u GOMP_SPINCOUNT PYTHONPATH=. $PY -m cluster.cli "${@:2}") > /dev/null; }
learn="bench learn --env skirmish/3m --algo qmix --target-win 0.95 --seeds 3"
train="bench train --env skirmish/bane_vs_bane --algo rdn --seeds 3 --steps 1500 --set run.torch_threads=0"
busy() { PYTHONPATH=. $PY -m cluster.cli bench load --seconds 900 > /dev/null & busy=$!; sleep 5; }  # from NEW
calm() {  # the load generator and its busy processes
  pkill -TERM -P $busy 2>/dev/null || true; kill $busy 2>/dev/null || true; wait $busy 2>/dev/null || true; }
side() {  # side NAME TREE ROUND: the 3m benchmark quiet and loaded, then bane_vs_bane RDN
  load "${3}_learn_$1"; credit $2 $learn --compare-load --out $NEW/$OUT/learn_3m_$1_$3.json
  load "${3}_train_$1_quiet"; credit $2 $train --out $NEW/$OUT/train_bvb_rdn_$1_quiet_$3.json
  busy; load "${3}_train_$1_loaded"
  credit $2 $train --out $NEW/$OUT/train_bvb_rdn_$1_loaded_$3.json; calm
}
for part in "${@:-round1}"; do
  case $part in
    round1) side old $OLD round1; side new $NEW round1 ;;
    round2) side new $NEW round2; side old $OLD round2 ;;
    fixed) load fixed_t2; credit $NEW $learn --compare-load --threads 2 --out $NEW/$OUT/learn_3m_new_t2.json ;;
    base) load base; credit $BASE $learn --out $NEW/$OUT/learn_3m_base.json ;;
  esac
done
load end

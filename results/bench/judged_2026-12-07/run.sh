#!/usr/bin/env bash
# Issue 35's judged command side by side, on one machine with nothing else running:
#   credit repro redundancy --envs skirmish/bane_vs_bane --algos rdn --seeds 3 --t-max 8000
#     --test-interval 4000 --workers 1
# under /usr/bin/time -v, from a worktree of 828260c (BASE, issue 35's baseline) and from this
# checkout, each with its own defaults (OMP_WAIT_POLICY/GOMP_SPINCOUNT unset), PYTHONPATH at the
# tree, the same venv. Round 1 runs the baseline first, round 2 this checkout first.
# Usage, from the repository root:
#   BASE=../wt/base results/bench/judged_2026-12-07/run.sh [round1|round2]...
set -euo pipefail
OUT=results/bench/judged_2026-12-07
PY=${PY:-$PWD/.venv/bin/python}  # not resolved: the symlink is what makes it the venv
NEW=$(pwd)
lscpu | grep -E "Model name" > $OUT/machine.txt
grep -o -w "amx_bf16\|avx512_bf16" /proc/cpuinfo | sort -u >> $OUT/machine.txt
echo "new $(git rev-parse HEAD) base $(git -C $BASE rev-parse HEAD)" >> $OUT/machine.txt
load() { echo "$1 $(date -u +%H:%M:%S) $(cut -d' ' -f1-3 /proc/loadavg)" >> $OUT/load.txt; }
judged() {  # judged NAME TREE ROUND
  local dir; dir=$(mktemp -d)
  load "${3}_$1_start"
  (cd $2 && env -u OMP_WAIT_POLICY -u GOMP_SPINCOUNT PYTHONPATH=. /usr/bin/time -v $PY -m cluster.cli \
    repro redundancy --envs skirmish/bane_vs_bane --algos rdn --seeds 3 --t-max 8000 \
    --test-interval 4000 --workers 1 --out $dir/out) > /dev/null 2> $dir/stderr
  load "${3}_$1_end"
  grep -E "Elapsed|Maximum resident|User time|System time" $dir/stderr > $NEW/$OUT/time_$1_$3.txt
  cp $dir/out/summary.json $NEW/$OUT/summary_$1_$3.json
  rm -rf $dir
}
for part in "${@:-round1}"; do
  case $part in
    round1) judged base $BASE round1; judged new $NEW round1 ;;
    round2) judged new $NEW round2; judged base $BASE round2 ;;
  esac
done
load end

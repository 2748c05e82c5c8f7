#!/bin/bash
# 3m learn bench at 39138e3 on the quiet AMD EPYC machine (2026-12-06): the shipped PASSIVE
# wait with auto threads ("default"), libgomp's spin policy with a short spin ("spin":
# OMP_WAIT_POLICY= GOMP_SPINCOUNT=10000) and one thread ("t1"), quiet in the order
# default spin t1 t1 spin default; then --compare-load (quiet, then beside `credit bench
# load`, one busy process per core) for default and spin. Run from the repo root.
D=results/bench/learn_3m/wait_39138e3
set_policy() {
  if [ "$1" = spin ]; then export GOMP_SPINCOUNT=10000 OMP_WAIT_POLICY=; else unset GOMP_SPINCOUNT OMP_WAIT_POLICY; fi
}
for t in default spin t1 t1 spin default; do
  n=$(ls $D/${t}_*.json 2>/dev/null | wc -l)
  set_policy $t; extra=; [ $t = t1 ] && extra="--threads 1"
  timeout 300 .venv/bin/python -m cluster.cli bench learn --env skirmish/3m --algo qmix --target-win 0.95 --seeds 3 $extra --out $D/${t}_$n.json > /dev/null 2>>$D/err.txt
  echo "$t $n rc=$? $(date +%T) $(cut -d' ' -f1-3 /proc/loadavg)" >> $D/log
done
for t in default spin; do
  set_policy $t
  timeout 600 .venv/bin/python -m cluster.cli bench learn --env skirmish/3m --algo qmix --target-win 0.95 --seeds 3 --compare-load --out $D/load_${t}.json > /dev/null 2>>$D/err.txt
  echo "load_$t rc=$? $(date +%T) $(cut -d' ' -f1-3 /proc/loadavg)" >> $D/log
done
# then, by hand, fixed two threads beside the load, short spin and shipped PASSIVE:
( export GOMP_SPINCOUNT=10000 OMP_WAIT_POLICY=; .venv/bin/python -m cluster.cli bench learn --env skirmish/3m --algo qmix --target-win 0.95 --seeds 3 --threads 2 --compare-load --out $D/load_spin_threads2.json )
.venv/bin/python -m cluster.cli bench learn --env skirmish/3m --algo qmix --target-win 0.95 --seeds 3 --threads 2 --compare-load --out $D/load_default_threads2.json

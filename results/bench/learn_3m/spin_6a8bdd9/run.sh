#!/bin/bash
# 3m learn bench at 6a8bdd9, quiet machine: libgomp defaults as shipped vs GOMP_SPINCOUNT=10000
cd /work/main
for t in default spin spin default; do
  n=$(ls /work/wt/quiet/w4/${t}_*.json 2>/dev/null | wc -l)
  if [ $t = spin ]; then export GOMP_SPINCOUNT=10000 OMP_WAIT_POLICY=; else unset GOMP_SPINCOUNT; unset OMP_WAIT_POLICY; fi
  timeout 300 .venv/bin/python -m cluster.cli bench learn --env skirmish/3m --algo qmix --target-win 0.95 --seeds 3 --out /work/wt/quiet/w4/${t}_$n.json > /dev/null 2>>/work/wt/quiet/w4/err.txt
  echo "$t $n $(date +%T) $(cut -d' ' -f1-3 /proc/loadavg)" >> /work/wt/quiet/w4/log
done

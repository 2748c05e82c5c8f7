#!/bin/bash
# Quiet window: pause both experiment chains (they checkpoint on SIGTERM and resume when
# rerun), then credit bench train old (8b0da3b, before passes) vs new (main) on bane_vs_bane.
set -u
OUT=/work/wt/quiet/w3; mkdir -p $OUT
PY=/work/main/.venv/bin/python
for pat in "out runs/t52b" "out runs/no_z2"; do
  P=$(pgrep -f "$pat" | head -1)
  [ -n "$P" ] && kill -TERM -- -$(ps -o pgid= -p $P | tr -d ' ')
done
echo "stopped $(date)" >> $OUT/log
while pgrep -f "runs/t52b|runs/no_z2" > /dev/null; do sleep 5; done
sleep 10; uptime >> $OUT/log
for round in 1 2; do
  for algo in rdn vdn qmix; do
    if [ $round = 1 ]; then order="old new"; else order="new old"; fi
    for t in $order; do
      if [ $t = old ]; then d=/work/wt/pre_passes; else d=/work/main; fi
      (cd $d && PYTHONPATH=$d OMP_NUM_THREADS=1 timeout 400 $PY -m cluster.cli bench train --env skirmish/bane_vs_bane --algo $algo --seeds 3 --steps 3000 --out $OUT/${algo}_${t}_r$round.json > /dev/null 2>>$OUT/err.txt)
      echo "$round $algo $t done $(date +%T) $(cut -d' ' -f1-3 /proc/loadavg)" >> $OUT/log
    done
  done
  [ -e $OUT/STOP_AFTER_1 ] && break
done
uptime >> $OUT/log
echo "window done $(date)" >> $OUT/log

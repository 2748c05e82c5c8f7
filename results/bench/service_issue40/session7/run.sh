#!/bin/bash
# Quiet window, session 7: credit bench service, 828260c (old828) vs 81ce8e0 (main), alternating.
set -u
OUT=/work/wt/quiet/w7; PY=/work/main/.venv/bin/python
uptime > $OUT/uptime_start.txt
for r in 1 2 3 4 5 6 7; do
  if [ $((r % 2)) = 1 ]; then order="old new"; else order="new old"; fi
  for t in $order; do
    if [ $t = old ]; then d=/work/wt/old828; else d=/work/main; fi
    (cd $d && PYTHONPATH=$d OMP_NUM_THREADS=1 timeout 300 $PY -m cluster.cli bench service --out $OUT/${t}_default_r$r.json > /dev/null 2>>$OUT/err.txt)
    echo "$r $t $(date +%T) $(cut -d' ' -f1-3 /proc/loadavg)" >> $OUT/log
  done
done
uptime > $OUT/uptime_end.txt
echo done >> $OUT/log

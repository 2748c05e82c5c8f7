#!/bin/bash
# Quiet window, session 8: credit bench service, 828260c (old828) against the tree at /work/main,
# alternating, with fsync (7 rounds) then with --no-fsync (5 rounds). Usage: run.sh OUT_DIR
set -u
OUT=$1; PY=/work/main/.venv/bin/python
mkdir -p $OUT
bench() {  # tree tag file extra-args
  if [ $1 = old ]; then d=/work/wt/old828; else d=/work/main; fi
  (cd $d && PYTHONPATH=$d OMP_NUM_THREADS=1 timeout 300 $PY -m cluster.cli bench service --out $3 $4 > /dev/null 2>>$OUT/err.txt)
}
bench new x $OUT/warmup.json ""  # numba's cache of the packing kernels, compiled once per tree
for mode in fsync nofsync; do
  if [ $mode = fsync ]; then rounds="1 2 3 4 5 6 7"; extra=""; else rounds="1 2 3 4 5"; extra="--no-fsync"; fi
  for r in $rounds; do
    if [ $((r % 2)) = 1 ]; then order="old new"; else order="new old"; fi
    for t in $order; do
      bench $t $t $OUT/${mode}_${t}_r$r.json "$extra"
      echo "$mode $r $t $(date +%T) $(cut -d' ' -f1-3 /proc/loadavg)" >> $OUT/log.txt
    done
  done
done
echo done >> $OUT/log.txt

#!/bin/bash
# The same short Table 5.1 command at e88aee4 (the commit of Table 5.1's first pairs) and at
# 30465cf (Table 5.2's commit, which has --seed-group), each from a worktree with PYTHONPATH
# at it; then compare the evaluation logs. Usage: run.sh WORKTREE_E88AEE4 WORKTREE_30465CF OUT
set -eu
for wt in "$1" "$2"; do
  tag=$(git -C "$wt" rev-parse --short HEAD)
  (cd "$wt" && PYTHONPATH="$wt" OMP_NUM_THREADS=1 python -m cluster.cli repro redundancy \
    --envs skirmish/bane_z4 --algos rdn,vdn,qmix,qmix_ns,iql --seeds 3 --t-max 6000 \
    --test-interval 3000 --workers 1 --out "$3/out_$tag") < /dev/null
done
python3 "$(dirname "$0")/compare.py" "$3/out_$(git -C "$1" rev-parse --short HEAD)/evals" \
  "$3/out_$(git -C "$2" rev-parse --short HEAD)/evals"

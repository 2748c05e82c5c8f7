"""torch.compile on the agents' GRU recurrence, forward and backward, against eager.

TORCHINDUCTOR_COMPILE_THREADS=1 python results/bench/tried_2026-12-06/compile_gru.py ROWS STEPS

One thread; E = 3 members of `EnsembleGRUCell` (hidden 64), ROWS rows per member (3m's batch:
32 episodes x 3 agents = 96), STEPS steps, from a precomputed input projection. Thread CPU
time, best of 5. Prints one JSON line: eager, one step compiled (dynamic rows) and the whole
STEPS-step loop compiled (specialised to STEPS), and the thread time each compilation took.
"""

import json
import sys
import time

import torch

from learner.networks import EnsembleGRUCell

torch.set_num_threads(1)
E, M, H, T = 3, int(sys.argv[1]), 64, int(sys.argv[2])
cell = EnsembleGRUCell(E, 10, H)
gi0 = torch.randn(E, T, M, 3 * H)


def loop(step):
    def run(gi):
        h, hs = gi.new_zeros(E, M, H), []
        for g in gi.unbind(1):
            h = step(g, h)
            hs.append(h)
        return torch.stack(hs, 1)

    return run


def bench(fn, reps=5):
    best = float("inf")
    for _ in range(reps):
        gi = gi0.clone().requires_grad_(True)
        t = time.thread_time()
        fn(gi).square().sum().backward()
        best = min(best, time.thread_time() - t)
    return best


def compiled(fn):
    t = time.thread_time()
    bench(fn, 1)
    return fn, time.thread_time() - t


eager = loop(cell.recur)  # the shipped step
step_c, step_compile_s = compiled(loop(torch.compile(cell.recur, dynamic=True)))
whole_c, whole_compile_s = compiled(torch.compile(loop(cell.recur)))
print(
    json.dumps(
        {
            "rows": M,
            "steps": T,
            "eager_s": round(bench(eager), 4),
            "step_compiled_s": round(bench(step_c), 4),
            "whole_loop_compiled_s": round(bench(whole_c), 4),
            "step_compile_thread_s": round(step_compile_s, 1),
            "whole_compile_thread_s": round(whole_compile_s, 1),
            "torch": torch.__version__,
        }
    )
)

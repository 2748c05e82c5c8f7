"""The agents' GRU recurrence as credit unrolls it (`learner.common.unroll`: one input
projection for every step, then `EnsembleGRUCell.recur` step by step in Python) against
PyTorch's whole-sequence GRU (`torch._VF.gru`, the C++ loop behind `nn.GRU`), one call per
ensemble member. Forward and backward of a sum of squares, thread CPU time, one torch
thread, best of 5; two rounds. Usage, from the repository root:

    PYTHONPATH=. python results/bench/tried_2026-12-07/fused_gru.py ROWS STEPS IN_FEATURES
"""

import json
import os
import sys
import time

import torch

from learner.networks import EnsembleGRUCell

torch.set_num_threads(1)
E, H = 3, 64
M, T, D = (int(a) for a in sys.argv[1:4])
torch.manual_seed(0)
cell = EnsembleGRUCell(E, D, H)
x = torch.randn(E, T, M, D)


def loop() -> torch.Tensor:
    gi = cell.ih(x.reshape(E, T * M, D)).view(E, T, M, -1)
    h = x.new_zeros(E, M, H)
    hs = []
    for g in gi.unbind(1):
        h = cell.recur(g, h)
        hs.append(h)
    return torch.stack(hs, 1)


def fused() -> torch.Tensor:
    out = []
    for e in range(E):
        params = [
            cell.ih.weight[e].t(),
            cell.hh.weight[e].t(),
            cell.ih.bias[e].reshape(-1),
            cell.hh.bias[e].reshape(-1),
        ]
        o, _ = torch._VF.gru(x[e], x.new_zeros(1, M, H), params, True, 1, 0.0, True, False, False)
        out.append(o)
    return torch.stack(out)


def best_ms(f) -> float:
    best = float("inf")
    for _ in range(5):
        for p in cell.parameters():
            p.grad = None
        t = time.thread_time()
        f().square().sum().backward()
        best = min(best, time.thread_time() - t)
    return round(best * 1e3, 1)


diff = (loop() - fused()).abs().max().item()
for r in range(2):
    row = {"rows": M, "steps": T, "in": D, "round": r, "loop_ms": best_ms(loop)}
    row |= {"fused_ms": best_ms(fused), "max_abs_diff": diff, "load_1m": os.getloadavg()[0]}
    print(json.dumps(row), flush=True)

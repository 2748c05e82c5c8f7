"""Two update speed-ups tried on 2026-12-06 and dropped (results/bench/NOTES.md, "Tried and
dropped"). Each is patched in here, not in the project, and timed against the shipped code
on one recorded random-policy batch (`cluster.bench.update.record_batch`), in thread CPU
time (`time.thread_time`), so that other processes on the machine stretch it less than
wall time; one thread.

    python results/bench/tried_2026-12-06/tried.py pad ENV ALGO      # output layer to 16
    python results/bench/tried_2026-12-06/tried.py mixer ENV qmix_ns  # sparse, fused mixer

`pad`: every EnsembleLinear narrower than 64 outputs is computed with its weight padded with
zero columns to a multiple of 16 (the products of [*, 32] x [32, 9] cost 3-4x those of
[32, 16] here). `mixer`: QMIX's four hypernetwork first layers in one product, and for
QMIX-nostate from the living agents' observations only (the joint observation's all-zero
agent blocks skipped). Prints one JSON line: milliseconds of thread CPU time per update,
old and new, per round, their ratio, and the largest parameter difference after one update
from the same initialisation.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np
import torch
from torch.nn import functional as F

from actors.envs.registry import make_vec_env
from cluster.alloc import keep_freed_memory
from cluster.bench.common import machine
from cluster.bench.update import record_batch
from cluster.config.train import load_train_config
from learner import networks
from learner.registry import get_algo

SHIPPED_LINEAR = networks.EnsembleLinear.forward
SHIPPED_MIXER = networks.QMixer.forward


def padded_linear(self, x):
    n = self.out_features
    pad = (-n) % 16
    if pad == 0 or n > 64:
        return SHIPPED_LINEAR(self, x)
    w, b = F.pad(self.weight, (0, pad)), F.pad(self.bias, (0, pad))
    return torch.baddbmm(b, x, w)[..., :n]


def _sparse_first(w, b, cond, n_agents):
    """cond [E, M, N*O] @ w [E, N*O, H] + b from the non-zero agent blocks only."""
    e, m, c = cond.shape
    o = c // n_agents
    x = cond.reshape(e, m, n_agents, o)
    ei, ii, mi = (x.abs().sum(-1) > 0).permute(0, 2, 1).nonzero().unbind(1)
    rows = x[ei, mi, ii]
    counts = torch.bincount(ei * n_agents + ii, minlength=e * n_agents).tolist()
    blocks = w.view(e, n_agents, o, -1)
    parts = [
        torch.mm(r, blocks[g // n_agents, g % n_agents])
        for g, r in enumerate(rows.split(counts))
        if r.shape[0]
    ]
    out = b.expand(e, m, -1).reshape(e * m, -1)
    if parts:
        out = out.index_add(0, ei * m + mi, torch.cat(parts))
    return out.view(e, m, -1)


def fused_mixer(self, qs, cond):
    e, m, n = qs.shape
    firsts = [self.hyper_w1.layers[0], self.hyper_w2.layers[0], self.hyper_b1]
    firsts.append(self.value.layers[0])
    w = torch.cat([f.weight for f in firsts], -1)
    b = torch.cat([f.bias for f in firsts], -1)
    # QMIX-nostate's cond is the joint observation: N blocks of O, all zero for the dead
    z = _sparse_first(w, b, cond, n) if MIXER_SPARSE else torch.baddbmm(b, cond, w)
    z1, z2, zb, zv = z.split([f.out_features for f in firsts], -1)
    w1 = self.hyper_w1.layers[1](F.relu(z1)).abs().view(e, m, n, self.embed)
    hidden = F.elu((qs.unsqueeze(-1) * w1).sum(-2) + zb)
    w2 = self.hyper_w2.layers[1](F.relu(z2)).abs()
    return (hidden * w2).sum(-1, keepdim=True) + self.value.layers[1](F.relu(zv))


MIXER_SPARSE = False  # set for qmix_ns by main
PATCHES = {
    "pad": (networks.EnsembleLinear, "forward", SHIPPED_LINEAR, padded_linear),
    "mixer": (networks.QMixer, "forward", SHIPPED_MIXER, fused_mixer),
}


def main(what: str, env: str, algo: str, rounds: int = 3, updates: int = 3) -> None:
    global MIXER_SPARSE
    MIXER_SPARSE = algo == "qmix_ns"
    torch.set_num_threads(1)
    keep_freed_memory()
    cls, name, old, new = PATCHES[what]
    batch = record_batch(env, 32, 3)
    cfg = load_train_config(algo, env, [], [])
    schema = make_vec_env(env, 1).info.schema()
    learners = {}
    for tag in ("old", "new"):
        torch.manual_seed(0)
        learners[tag] = get_algo(algo).build(cfg.algo, schema, 3, "cpu")
    steps = {"old": old, "new": new}
    for tag, learner in learners.items():
        setattr(cls, name, steps[tag])
        learner.step(batch)
    params = {t: [p.detach() for p in lr.updater.params] for t, lr in learners.items()}
    diff = max((a - b).abs().max().item() for a, b in zip(*params.values(), strict=True))
    ms: dict[str, list[float]] = {"old": [], "new": []}
    for _ in range(rounds):
        for tag, learner in learners.items():
            setattr(cls, name, steps[tag])
            started = time.thread_time()
            for _ in range(updates):
                learner.step(batch)
            ms[tag].append(round((time.thread_time() - started) / updates * 1000, 1))
    setattr(cls, name, old)
    ratio = float(np.median(ms["old"]) / np.median(ms["new"]))
    record = {"tried": what, "env": env, "algo": algo, "seeds": 3, "batch_episodes": 32}
    record |= {"thread_cpu_ms_per_update": ms, "old_over_new": round(ratio, 3)}
    record |= {"max_param_diff_after_one_update": diff, "machine": machine()}
    print(json.dumps(record))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3])

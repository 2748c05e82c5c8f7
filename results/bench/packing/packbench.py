"""PackedEpisode.pack per episode (us), best of 5 timeit repeats, one thread.

Run from a checkout's root with PYTHONPATH at it: python results/bench/packing/packbench.py TAG
"""

import json
import sys
import timeit

import numpy as np

from buffer_service.episode import EpisodeSchema
from buffer_service.packed import PackedEpisode
from cluster.bench.common import synthetic_episode
from cluster.bench.service import SIZES
from tests.buffer_service.test_packed import smac_like

BANE = EpisodeSchema(n_agents=24, obs_dim=336, state_dim=984, n_actions=30, max_t=200)
CASES = {
    "3m_synthetic_dense": synthetic_episode(SIZES["3m"], 60, 0, np.random.default_rng(0), 0),
    "bane_synthetic_dense": synthetic_episode(
        SIZES["bane_vs_bane"], 200, 0, np.random.default_rng(0), 0
    ),
    "bane_smac_like_sparse_t120": smac_like(0, 120, BANE),
}
out = {"tree": sys.argv[1]}
for name, ep in CASES.items():
    PackedEpisode.pack(ep)
    n = 2000 if name.startswith("3m") else 20
    best = min(timeit.repeat(lambda ep=ep: PackedEpisode.pack(ep), number=n, repeat=5))
    out[name + "_us"] = round(best / n * 1e6, 1)
print(json.dumps(out))

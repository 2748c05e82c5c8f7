"""A 3 x 32-episode batch (EpisodeBatch.from_members) from packed and from dense episodes
(ms), best of 5 timeit repeats, one thread.

Run from a checkout's root with PYTHONPATH at it: python results/bench/packing/decbench.py TAG
"""

import json
import sys
import timeit

from buffer_service.episode import EpisodeBatch, EpisodeSchema
from buffer_service.packed import PackedEpisode
from tests.buffer_service.test_packed import smac_like

THREE = EpisodeSchema(n_agents=3, obs_dim=30, state_dim=48, n_actions=9, max_t=60)
BANE = EpisodeSchema(n_agents=24, obs_dim=336, state_dim=984, n_actions=30, max_t=200)


def best_ms(members, n):
    EpisodeBatch.from_members(members)
    return round(
        min(timeit.repeat(lambda: EpisodeBatch.from_members(members), number=n, repeat=5))
        / n
        * 1e3,
        3,
    )


out = {"tree": sys.argv[1]}
for name, schema, t, n in (("3m", THREE, 25, 500), ("bane", BANE, 60, 5)):
    dense = [smac_like(i, t, schema) for i in range(32)]
    packed = [PackedEpisode.pack(ep) for ep in dense]
    out[name + "_batch_3x32_ms"] = best_ms([packed] * 3, n)
    out[name + "_dense_batch_3x32_ms"] = best_ms([dense] * 3, n)
print(json.dumps(out))

"""A replay's byte budget: the oldest episodes go, and the process's memory stays put."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

from buffer_service.config import TableConfig
from buffer_service.local import LocalBuffer
from buffer_service.packed import PackedEpisode
from tests.buffer_service.conftest import SCHEMA, make_episode

MIB = 2**20

# Fill a replay of a 16 MiB budget with 4x that in packed episodes while an "update" (a
# 48 MiB block, allocated, touched and freed) runs every 10 inserts, under the training's
# allocator settings (run.keep_freed_memory); print the table and the resident sizes.
CHILD = textwrap.dedent(
    """
    import dataclasses, json, sys
    import numpy as np
    from cluster.alloc import keep_freed_memory
    from buffer_service.config import TableConfig
    from buffer_service.episode import EpisodeSchema
    from buffer_service.local import LocalBuffer
    from buffer_service.packed import PackedEpisode
    from tests.buffer_service.test_packed import smac_like

    def rss():
        for line in open("/proc/self/status"):
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024

    kept = keep_freed_memory()
    budget = 16 * 2**20
    wide = EpisodeSchema(n_agents=24, obs_dim=80, state_dim=30, n_actions=9, max_t=60)
    pool = [smac_like(i, 60, wide) for i in range(20)]
    buf = LocalBuffer((TableConfig("replay", "replay", capacity=10**6, max_bytes=budget),))
    table = buf.state.tables["replay"]
    PackedEpisode.pack(pool[0])  # load the packing kernels (a fixed cost, not the replay's)
    start, full, inserted, i = rss(), None, 0, 0
    while inserted < 4 * budget:
        ep = dataclasses.replace(pool[i % len(pool)], episode_seq=i)
        buf.insert([ep])
        inserted += PackedEpisode.pack(ep).nbytes
        if i % 10 == 0:
            update = np.ones(12 * 2**20, np.float32)  # 48 MiB, touched
            del update
        if full is None and table.evicted:
            full = rss()
        i += 1
    print(json.dumps({
        "kept": kept, "budget": budget, "inserted_bytes": inserted, "episodes": i,
        "table_bytes": table.bytes, "keys": [k[1] for k in table.order],
        "evicted": table.evicted, "rss_start": start, "rss_full": full, "rss_end": rss(),
    }))
    """
)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/status")
def test_a_replay_past_its_budget_evicts_the_oldest_and_holds_its_memory():
    out = subprocess.run(
        [sys.executable, "-c", CHILD], capture_output=True, text=True, check=True
    ).stdout
    r = json.loads(out.strip().splitlines()[-1])
    budget = r["budget"]
    assert r["inserted_bytes"] >= 4 * budget
    assert 0 < r["table_bytes"] <= budget
    # FIFO: what is left is the newest episodes, in insertion order; the rest was evicted
    keys = r["keys"]
    assert keys == list(range(r["episodes"] - len(keys), r["episodes"]))
    assert r["evicted"] == r["episodes"] - len(keys) > 0
    # Memory held (generous bounds, no timing): from the first eviction to the end, three
    # more budgets' worth of episodes came and went; the process grew by far less than one.
    assert r["rss_end"] - r["rss_full"] <= budget // 4 + 8 * MIB, r
    # and in all it holds the budget, the update's 48 MiB block and little else
    assert r["rss_end"] - r["rss_start"] <= budget + 48 * MIB + budget // 2, r


def test_byte_budget_counts_packed_sizes_and_applies_to_both_kinds():
    for kind in ("replay", "cycling"):
        ep = PackedEpisode.pack(make_episode(0, 0, t=5))
        cfg = TableConfig("t", kind, capacity=100, max_times_sampled=0, max_bytes=3 * ep.nbytes)
        buf = LocalBuffer((cfg,), schema=SCHEMA)
        buf.insert([make_episode(0, i, t=5) for i in range(5)])
        stats = buf.stats()["tables"]["t"]
        assert stats["size"] == 3 and stats["evicted"] == 2 and stats["bytes"] == 3 * ep.nbytes
        assert sorted(buf.state.episodes) == [(0, 2), (0, 3), (0, 4)]


def test_a_smaller_budget_on_restore_drops_the_oldest(tmp_path):
    ep = PackedEpisode.pack(make_episode(0, 0, t=5))
    big = TableConfig("replay", "replay", capacity=100, max_bytes=10 * ep.nbytes)
    buf = LocalBuffer((big,), schema=SCHEMA)
    buf.insert([make_episode(0, i, t=5) for i in range(8)])
    buf.write(tmp_path / "snap")
    small = TableConfig("replay", "replay", capacity=100, max_bytes=5 * ep.nbytes)
    back = LocalBuffer((small,), schema=SCHEMA)
    back.read(tmp_path / "snap")
    table = back.state.tables["replay"]
    assert list(table.order) == [(0, i) for i in range(3, 8)]
    assert table.bytes == 5 * ep.nbytes and sorted(back.state.episodes) == list(table.order)

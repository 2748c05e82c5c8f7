"""Pure parts of `credit bench scaling`, with hand-computed values (no timings asserted)."""

from __future__ import annotations

import pytest

from buffer_service.client import BufferClient, RateLimitedError
from buffer_service.config import BufferConfig, RateLimiterConfig, TableConfig
from buffer_service.runner import start_server_thread
from cluster.bench import scaling_stats as st
from cluster.bench.scaling import limiter_off
from cluster.metrics.loop_stats import LoopStats
from tests.buffer_service.conftest import SCHEMA, make_episode

# /proc/<pid>/stat of a process whose name has a space and a ')' in it; utime 120, stime 30.
STAT = (
    "4242 (ray::Rollout) x) S 4000 4242 4000 0 -1 4194560 1000 0 0 0 "
    "120 30 0 0 20 0 12 0 5000 100000 2000 18446744073709551615"
)


def test_parse_proc_stat_counts_fields_after_the_last_paren():
    assert st.parse_proc_stat(STAT) == (4000, 150)


def test_parse_machine_stat_busy_excludes_idle_and_iowait():
    text = "cpu  100 5 50 800 40 3 2 0 7 0\ncpu0 50 2 25 400 20 1 1 0 0 0\nintr 1 2\n"
    # total = 100+5+50+800+40+3+2+0 = 1000; busy = 1000 - 800 - 40 = 160
    assert st.parse_machine_stat(text) == (160, 1000)
    with pytest.raises(ValueError):
        st.parse_machine_stat("intr 1 2\n")


def test_group_ticks_sorts_the_process_tree():
    # 1 -> learner 10 -> {buffer 11, raylet 12 -> {actor 13, actor 14, idle 15}}; 99 elsewhere
    table = {
        1: (0, 0),
        10: (1, 500),
        11: (10, 70),
        12: (10, 9),
        13: (12, 200),
        14: (12, 100),
        15: (12, 1),
        99: (1, 10_000),
    }
    assert st.descendants(table, 10) == {11, 12, 13, 14, 15}
    got = st.group_ticks(table, learner=10, buffer=11, actors=[13, 14, 77])  # 77 is gone
    assert got == {"learner": 500, "buffer": 70, "actors": 300, "ray_system": 10}


def test_lag_summary_mean_and_nearest_rank_p95():
    # 20 episodes: lags 0 x10, 1 x5, 2 x4, 9 x1 -> mean (0+5+8+9)/20 = 1.1; rank ceil(19) = 19
    # -> the 19th smallest is a 2 (positions 16..19).
    assert st.lag_summary({0: 10, 1: 5, 2: 4, 9: 1}) == {"mean": 1.1, "p95": 2.0, "episodes": 20}
    assert st.lag_summary({3: 1}) == {"mean": 3.0, "p95": 3.0, "episodes": 1}
    assert st.lag_summary({}) == {"mean": None, "p95": None, "episodes": 0}


def test_counts_delta_accepts_json_string_keys():
    assert st.counts_delta({0: 5, 1: 7, 2: 1}, {"0": 5, "1": 3}) == {1: 4, 2: 1}


def _snap(t, t_env, episodes, updates, consumed, sample_s, update_s, lags, ticks, machine, waits):
    loop = LoopStats(updates=updates, consumed_env_steps=consumed, sample_requests=updates)
    loop.sample_s, loop.update_s = sample_s, update_s
    loop.lag_counts.update(lags)
    return {
        "t": t,
        "t_env": t_env,
        "episodes": episodes,
        "learner": loop.snapshot(),
        "buffer": {
            "tables": {"replay": {"size": episodes}},
            "limiter_waits": {
                "insert": {"count": 0, "seconds": 0.0, "timeouts": 0},
                "sample": {"count": waits[0], "seconds": waits[1], "timeouts": 0},
            },
        },
        "actors": [dict(pid=5, act_s=t * 0.8, insert_s=t * 0.1, sync_s=t * 0.1, insert_refusals=0)],
        "cpu_ticks": dict(zip(st.CPU_GROUPS, ticks, strict=True)),
        "machine_ticks": machine,
    }


def test_window_figures_by_hand():
    old = _snap(10.0, 1000, 50, 4, 2560, 1.0, 2.0, [0, 0, 1], (100, 10, 200, 5), (0, 0), (1, 0.5))
    new = _snap(
        12.0, 3000, 150, 14, 9000, 1.5, 3.0, [0, 0, 1, 1, 2, 3], (200, 30, 400, 7), (300, 400),
        (5, 1.5),
    )  # fmt: skip
    w = st.window_figures(old, new, clk_tck=100, ncpu=2)
    assert w["seconds"] == 2.0
    assert w["insert_env_steps_per_s"] == 1000.0  # 2000 steps / 2 s
    assert w["insert_episodes_per_s"] == 50.0
    assert w["learner_env_steps_per_s"] == 3220.0  # (9000 - 2560) / 2
    assert w["updates_per_s"] == 5.0
    assert w["learner_time"] == {
        "sampling_fraction": 0.25,
        "updating_fraction": 0.5,
        "publishing_fraction": 0.0,
    }
    cores = w["cpu_cores"]  # ticks / 100 per s / 2 s
    assert (cores["learner"], cores["buffer"], cores["actors"]) == (0.5, 0.1, 1.0)
    assert cores["ray_system"] == pytest.approx(0.01)
    assert cores["total"] == pytest.approx(1.61)
    assert cores["machine_busy"] == 1.5  # 2 CPUs x 300/400
    assert cores["others"] == 0.0  # machine busy 1.5 < ours 1.61 (sampling skew): clipped
    # 0.5 cores x 2 s = 1 s of learner CPU for 2000 inserted steps = 0.5 ms per step
    assert w["cpu_ms_per_inserted_step"]["learner"] == 0.5
    assert w["policy_lag"] == {"mean": 2.0, "p95": 3.0, "episodes": 3}  # lags 1, 2, 3
    assert w["limiter"]["sample"] == {
        "held_per_s": 2.0,
        "held_fraction_of_time": 0.5,
        "timeouts": 0,
    }
    assert w["actors"]["acting_fraction"] == pytest.approx(0.8)
    assert w["buffer_size"] == {"replay": 150}


def test_median_tree_takes_leafwise_medians_and_skips_none():
    windows = [
        {"a": 1.0, "b": {"c": 10, "d": None}, "s": "x"},
        {"a": 3.0, "b": {"c": 30, "d": 4.0}, "s": "x"},
        {"a": 2.0, "b": {"c": 20, "d": None}, "s": "x"},
    ]
    assert st.median_tree(windows) == {"a": 2.0, "b": {"c": 20, "d": 4.0}, "s": "x"}
    assert st.median_tree([{"d": None}, {"d": None}]) == {"d": None}


def test_efficiency_against_the_smallest_count():
    # T(1) = 100, T(2) = 150 -> 150 / (2 x 100) = 0.75; T(4) = 200 -> 200 / 400 = 0.5
    assert st.efficiency({2: 150.0, 1: 100.0, 4: 200.0}) == {1: 1.0, 2: 0.75, 4: 0.5}
    # without N = 1: against N0 = 2: T(4) / (4/2 x T(2)) = 240 / 300 = 0.8
    assert st.efficiency({2: 150.0, 4: 240.0}) == {2: 1.0, 4: 0.8}
    assert st.efficiency({1: 0.0, 2: 5.0}) == {1: None, 2: None}


def test_rounded_keeps_structure():
    assert st.rounded({"a": [1.234567, 2], "b": None}, 3) == {"a": [1.23, 2], "b": None}


def test_limiter_off_keeps_min_size_and_drops_the_ratio():
    t = TableConfig(
        name="replay",
        kind="replay",
        capacity=100,
        rate_limiter=RateLimiterConfig(min_size_to_sample=32, samples_per_insert=4.0,
                                       error_buffer=128),
    )  # fmt: skip
    (off,) = limiter_off((t,))
    assert off.capacity == 100 and off.name == "replay"
    assert off.rate_limiter.min_size_to_sample == 32
    assert off.rate_limiter.samples_per_insert == 0.0


def test_server_counts_requests_the_limiter_held_back():
    tables = (
        TableConfig(
            name="replay",
            kind="replay",
            capacity=10,
            rate_limiter=RateLimiterConfig(min_size_to_sample=2),
        ),
    )
    srv = start_server_thread(BufferConfig(schema=SCHEMA, tables=tables, sample_timeout_s=5.0))
    client = BufferClient("127.0.0.1", srv.port, max_retries=2)
    try:
        with pytest.raises(RateLimitedError):
            client.sample("replay", 1, timeout_s=0.05)  # held back: fewer than 2 stored
        client.insert([make_episode(0, i) for i in range(2)])
        client.sample("replay", 1)  # allowed at once: not counted
        waits = client.stats()["limiter_waits"]
        assert waits["sample"]["count"] == 1 and waits["sample"]["timeouts"] == 1
        assert waits["sample"]["seconds"] > 0
        assert waits["insert"] == {"count": 0, "seconds": 0.0, "timeouts": 0}
    finally:
        client.close()
        srv.stop(snapshot=False)


@pytest.mark.parametrize("no_fsync", [False, True])
def test_the_benchmarks_config_loads(no_fsync):
    """Every key the benchmark sets is one the config takes (a renamed key failed here only
    when the benchmark ran)."""
    import argparse

    from cluster.bench.scaling import _config

    args = argparse.Namespace(algo="rdn", env="skirmish/3m", no_fsync=no_fsync, set=[])
    cfg = _config(args, 4, 0.5)
    assert (cfg.cluster.actors, cfg.cluster.metrics) == (4, False)
    assert cfg.cluster.fsync is not no_fsync

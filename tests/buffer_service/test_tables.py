"""Table and rate-limiter bookkeeping, with hand-computed expectations."""

from __future__ import annotations

import random

import pytest

from buffer_service.config import BufferConfig, RateLimiterConfig, TableConfig
from buffer_service.tables import RateLimiter, Table


def test_sample_to_insert_ratio_by_hand():
    # spi=2, min_size=2, error_buffer=2: offset=4, samples allowed while diff-n >= 2,
    # inserts while diff+2 <= 6, where diff = 2*inserts - samples.
    lim = RateLimiter(RateLimiterConfig(min_size_to_sample=2, samples_per_insert=2, error_buffer=2))
    assert lim.can_insert() and not lim.can_sample(1, size=0)
    lim.inserts = 2  # diff = 4
    assert lim.can_sample(1, size=2)  # 3 >= 2
    assert lim.can_sample(2, size=2)  # 2 >= 2
    assert not lim.can_sample(3, size=2)  # 1 < 2
    assert not lim.can_sample(1, size=1)  # below min size
    assert lim.can_insert()  # 6 <= 6
    lim.inserts = 3  # diff = 6
    assert not lim.can_insert()  # 8 > 6
    lim.samples = 4  # diff = 2
    assert lim.can_insert() and not lim.can_sample(1, size=3)


def test_min_size_only_limiter():
    lim = RateLimiter(RateLimiterConfig(min_size_to_sample=3))
    lim.inserts = 100
    assert not lim.can_sample(1, size=2) and lim.can_sample(50, size=3) and lim.can_insert()


def test_cycling_drops_oldest_and_retires_after_k():
    t = Table(TableConfig(name="c", kind="cycling", capacity=3, max_times_sampled=2))
    dropped = [t.insert((0, i)) for i in range(4)]
    assert dropped == [[], [], [], [(0, 0)]]
    assert list(t.order) == [(0, 1), (0, 2), (0, 3)]
    assert t.mark_sampled([(0, 1), (0, 2)]) == []
    assert t.mark_sampled([(0, 1)]) == [(0, 1)]
    assert list(t.order) == [(0, 2), (0, 3)]
    assert t.stats()["retired"] == 1 and t.stats()["evicted"] == 1
    assert not t.ready(3) and t.ready(2)  # cycling never repeats within a batch
    assert sorted(t.choose(2, random.Random(0))) == [(0, 2), (0, 3)]


def test_replay_uniform_with_replacement_and_capacity():
    t = Table(TableConfig(name="r", kind="replay", capacity=10))
    for i in range(15):
        t.insert((1, i))
    assert list(t.order) == [(1, i) for i in range(5, 15)]
    keys = t.choose(20_000, random.Random(1))
    counts = {k: keys.count(k) for k in t.order}
    assert set(keys) == set(t.order)
    assert all(1700 < c < 2300 for c in counts.values()), counts  # 2000 expected each
    assert t.mark_sampled(keys[:100]) == []  # K never retires replay items
    assert t.ready(50)  # with replacement: a batch may exceed the size


def test_table_state_round_trip():
    t = Table(TableConfig(name="c", kind="cycling", capacity=4, max_times_sampled=3))
    for i in range(5):
        t.insert((2, i))
    t.mark_sampled([(2, 3), (2, 3)])
    u = Table(t.cfg)
    u.load_state(t.to_state())
    assert list(u.order) == list(t.order) and u.times_sampled == t.times_sampled
    assert u.stats() == t.stats()


@pytest.mark.parametrize(
    ("kw", "field"),
    [
        ({"host": "0.0.0.0"}, "token"),
        ({"host": "10.1.2.3", "token": ""}, "token"),
        ({"port": 70000}, "port"),
        ({"tables": ()}, "tables"),
        ({"tables": (TableConfig(name="a"), TableConfig(name="a"))}, "duplicate"),
        ({"tables": (TableConfig(kind="lifo"),)}, "table.kind"),
        ({"tables": (TableConfig(capacity=0),)}, "table.capacity"),
        ({"max_frame_bytes": 10}, "max_frame_bytes"),
        ({"sample_timeout_s": 0}, "sample_timeout_s"),
        (
            {
                "tables": (
                    TableConfig(
                        rate_limiter=RateLimiterConfig(samples_per_insert=4, error_buffer=1)
                    ),
                )
            },
            "error_buffer",
        ),
    ],
)
def test_config_validate_names_the_field(kw, field):
    with pytest.raises(ValueError, match=field):
        BufferConfig(**kw).validate()


def test_loopback_hosts_need_no_token():
    for host in ("127.0.0.1", "127.0.0.5", "::1", "localhost"):
        BufferConfig(host=host).validate()


def test_replay_without_replacement_never_repeats_within_a_batch():
    t = Table(TableConfig(name="r", kind="replay", capacity=10, replacement=False))
    for i in range(6):
        t.insert((1, i))
    assert t.ready(6) and not t.ready(7)  # a batch needs that many distinct episodes
    rng = random.Random(3)
    for _ in range(200):
        keys = t.choose(6, rng)
        assert sorted(keys) == [(1, i) for i in range(6)]

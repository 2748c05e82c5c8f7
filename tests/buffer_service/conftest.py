"""Shared helpers: a small schema, episode factory, and an in-process server fixture."""

from __future__ import annotations

import numpy as np
import pytest

from buffer_service.client import BufferClient
from buffer_service.config import BufferConfig, RateLimiterConfig, TableConfig
from buffer_service.episode import Episode, EpisodeSchema
from buffer_service.runner import start_server_thread

SCHEMA = EpisodeSchema(n_agents=3, obs_dim=5, state_dim=7, n_actions=4, max_t=10)


def make_episode(actor: int = 0, seq: int = 0, t: int = 5, schema: EpisodeSchema = SCHEMA):
    """A valid episode whose reward[0] encodes (actor, seq) so tests can identify it."""
    rng = np.random.default_rng(actor * 100_003 + seq)
    n, a = schema.n_agents, schema.n_actions
    reward = np.zeros(t, np.float32)
    reward[0] = actor * 1000 + seq
    return Episode(
        obs=rng.random((t + 1, n, schema.obs_dim), dtype=np.float32),
        state=rng.random((t + 1, schema.state_dim), dtype=np.float32),
        avail_actions=np.ones((t + 1, n, a), np.uint8),
        actions=rng.integers(0, a, (t, n)).astype(np.int64),
        reward=reward,
        terminated=np.eye(1, t, t - 1, dtype=bool)[0],
        filled=np.ones(t, bool),
        actor_id=actor,
        episode_seq=seq,
        policy_version=seq // 2,
    )


def table(name: str, kind: str, capacity: int, k: int = 0, **limiter) -> TableConfig:
    return TableConfig(
        name=name,
        kind=kind,
        capacity=capacity,
        max_times_sampled=k,
        rate_limiter=RateLimiterConfig(**limiter),
    )


@pytest.fixture
def serve():
    """Factory: serve(**BufferConfig fields) -> (ServerThread, BufferClient); all stopped after."""
    started = []

    def _serve(**kw):
        kw.setdefault("schema", SCHEMA)
        kw.setdefault("sample_timeout_s", 5.0)
        srv = start_server_thread(BufferConfig(**kw))
        client = BufferClient("127.0.0.1", srv.port, token=kw.get("token"), max_retries=2)
        started.append((srv, client))
        return srv, client

    yield _serve
    for srv, client in started:
        client.close()
        srv.stop(snapshot=False)

"""Batching episodes: one batch per ensemble member, stacked [E, B, ...]."""

from __future__ import annotations

import dataclasses
import mmap

import numpy as np
import pytest

from buffer_service import episode as episode_module
from buffer_service.episode import EpisodeBatch, EpisodeError
from tests.buffer_service.conftest import make_episode


def test_from_members_equals_padding_each_member_then_stacking():
    # members of different longest episodes: member 1's batch is padded further by `stack`
    members = [
        [make_episode(0, 0, t=3), make_episode(0, 1, t=6)],
        [make_episode(1, 0, t=9), make_episode(1, 1, t=2)],
        [make_episode(2, 0, t=4), make_episode(2, 1, t=4)],
    ]
    direct = EpisodeBatch.from_members(members)
    stacked = EpisodeBatch.stack([EpisodeBatch.from_episodes(m) for m in members])
    for f in dataclasses.fields(EpisodeBatch):
        a, b = getattr(direct, f.name), getattr(stacked, f.name)
        assert a.dtype == b.dtype and a.shape == b.shape, f.name
        np.testing.assert_array_equal(a, b, err_msg=f.name)
    assert direct.avail_actions[1, 1, 5:, :, 0].all()  # padding: the no-op only


def test_from_members_refuses_members_of_different_sizes():
    with pytest.raises(EpisodeError, match=r"different numbers of episodes: \[1, 2\]"):
        EpisodeBatch.from_members([[make_episode(0, 0)], [make_episode(1, 0), make_episode(1, 1)]])


def test_a_large_batch_lives_in_mappings_of_its_own_with_the_same_values(monkeypatch):
    """Batch arrays of at least BATCH_MAPPED_MIN_BYTES come from anonymous mappings (off
    malloc's heap, see `batch_zeros`), smaller ones from the heap; both hold what a heap
    batch holds, padding included, and are writable like one."""
    members = [[make_episode(m, k, t=3 + 2 * k + m) for k in range(3)] for m in range(2)]
    heap = EpisodeBatch.from_members(members)
    time_fields = ("obs", "state", "avail_actions", "actions", "reward", "terminated", "filled")
    assert not any(_mapped(getattr(heap, name)) for name in time_fields)
    monkeypatch.setattr(episode_module, "BATCH_MAPPED_MIN_BYTES", 64)
    mapped = EpisodeBatch.from_members(members)
    assert _mapped(mapped.obs) and _mapped(mapped.state) and _mapped(mapped.avail_actions)
    for f in dataclasses.fields(EpisodeBatch):
        a, b = getattr(mapped, f.name), getattr(heap, f.name)
        assert a.dtype == b.dtype and a.shape == b.shape, f.name
        np.testing.assert_array_equal(a, b, err_msg=f.name)
    mapped.obs[0, 0, 0, 0, 0] = 7.0
    assert mapped.obs[0, 0, 0, 0, 0] == 7.0


def _mapped(a: np.ndarray) -> bool:
    """Whether a's memory is an anonymous mapping (`batch_zeros`), through any views."""
    while isinstance(a.base, np.ndarray):
        a = a.base
    return isinstance(getattr(a.base, "obj", a.base), mmap.mmap)

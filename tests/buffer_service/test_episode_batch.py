"""Batching episodes: one batch per ensemble member, stacked [E, B, ...]."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

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

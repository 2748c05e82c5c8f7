"""The PettingZoo wrapper passes PettingZoo's own parallel API test on every map."""

import numpy as np
import pytest

pytest.importorskip("pettingzoo")
from pettingzoo.test import parallel_api_test

from actors.envs.pettingzoo import parallel_env
from actors.envs.registry import env_ids

ENV_IDS = [e for e in env_ids() if e.startswith(("skirmish/", "matrix/"))]


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_parallel_api(env_id):
    env = parallel_env(env_id, seed=0)
    parallel_api_test(env, num_cycles=400)


def test_masks_and_team_reward():
    env = parallel_env("skirmish/3m", seed=0)
    obs, _ = env.reset(seed=1)
    assert env.agents == ["agent_0", "agent_1", "agent_2"]
    assert obs["agent_0"]["action_mask"].tolist()[:2] == [0, 1]  # alive: no no-op, stop
    assert env.state().shape == (48,)
    total, done = 0.0, False
    while env.agents:
        acts = {a: int(np.flatnonzero(obs[a]["action_mask"])[-1]) for a in env.agents}
        obs, rew, term, trunc, _ = env.step(acts)
        assert len(set(rew.values())) == 1
        total += next(iter(rew.values()))
        done = any(term.values()) or any(trunc.values())
    assert done and total >= 0

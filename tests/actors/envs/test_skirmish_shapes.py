"""Skirmish sizes equal SMAC's and every registered skirmish map runs."""

import numpy as np
import pytest

from actors.envs.registry import env_ids, make_env, make_vec_env

# SMAC (oxwhirl) defaults: obs / state / n_actions, plus agents, enemies, limit.
SMAC_SIZES = [
    ("3m", 30, 48, 9, 3, 3, 60),
    ("2s3z", 80, 120, 11, 5, 5, 120),
    ("3s5z", 128, 216, 14, 8, 8, 150),
    ("1c3s5z", 162, 270, 15, 9, 9, 180),
    ("MMM2", 176, 322, 18, 10, 12, 180),
    ("2c_vs_64zg", 332, 342, 70, 2, 64, 400),
    ("bane_vs_bane", 336, 984, 30, 24, 24, 200),
    ("8m", 80, 168, 14, 8, 8, 120),
]
ALL_MAPS = [
    "3m", "8m", "2s3z", "3s5z", "1c3s5z", "MMM2", "2c_vs_64zg",
    "bane_vs_bane", "bane_med", "bane_small", "bane_no_z",
]  # fmt: skip
VARIANT_AGENTS = {"bane_med": 19, "bane_small": 14, "bane_no_z": 4}


@pytest.mark.parametrize(
    ("name", "obs", "state", "actions", "agents", "enemies", "limit"), SMAC_SIZES
)
def test_sizes_equal_smac(name, obs, state, actions, agents, enemies, limit):
    env = make_env(f"skirmish/{name}", seed=0)
    info = env.get_env_info()
    assert (info["obs_shape"], info["state_shape"], info["n_actions"]) == (obs, state, actions)
    assert (info["n_agents"], info["n_enemies"], info["episode_limit"]) == (agents, enemies, limit)
    assert info["has_wins"] is True
    o, s = env.reset()
    assert o.shape == (agents, obs) and s.shape == (state,)
    assert env.get_avail_actions().shape == (agents, actions)


@pytest.mark.parametrize("name", ALL_MAPS)
def test_every_map_is_registered_and_runs(name):
    assert f"skirmish/{name}" in env_ids()
    venv = make_vec_env(f"skirmish/{name}", 3, seed=1)
    venv.reset()
    rng = np.random.default_rng(0)
    info = venv.info
    for _ in range(5):
        avail = venv.get_avail_actions()
        obs, state = venv.get_obs(), venv.get_state()
        assert obs.shape == (3, info.n_agents, info.obs_shape) and obs.dtype == np.float32
        assert state.shape == (3, info.state_shape)
        assert np.isfinite(obs).all() and np.isfinite(state).all()
        acts = (avail * rng.random(avail.shape)).argmax(-1)
        reward, term, infos = venv.step(acts, np.ones(3, bool))
        assert reward.shape == (3,) and (reward >= 0).all() and not term.any()
        assert all(set(i) >= {"battle_won", "episode_limit"} for i in infos)
    if name in VARIANT_AGENTS:
        assert info.n_agents == VARIANT_AGENTS[name] and info.n_enemies == 24
        assert info.n_actions == 30

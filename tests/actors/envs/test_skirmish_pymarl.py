"""The README's PyMARL-family recipe: the `smac.env` shim and a PyMARL-style episode loop
with the env_args of EPyMARL's and PyMARL's shipped `sc2` configs."""

import importlib
import sys

import numpy as np
import pytest
import torch

from actors.envs.base import EnvError
from actors.envs.skirmish import StarCraft2Env, smac_shim_path

# env_args of EPyMARL's src/config/envs/sc2.yaml (PyMARL's and PyMARL2's differ only in
# state_last_action: True).
EPYMARL_SC2 = {
    "continuing_episode": False, "difficulty": "7", "game_version": None, "map_name": "3m",
    "move_amount": 2, "obs_all_health": True, "obs_instead_of_state": False,
    "obs_last_action": False, "obs_own_health": True, "obs_pathing_grid": False,
    "obs_terrain_height": False, "obs_timestep_number": False, "reward_death_value": 10,
    "reward_defeat": 0, "reward_negative_scale": 0.5, "reward_only_positive": True,
    "reward_scale": True, "reward_scale_rate": 20, "reward_sparse": False, "reward_win": 200,
    "replay_dir": "", "replay_prefix": "", "state_last_action": False,
    "state_timestep_number": False, "step_mul": 8, "seed": None, "heuristic_ai": False,
    "heuristic_rest": False, "debug": False,
}  # fmt: skip
PYMARL_SC2 = {**EPYMARL_SC2, "state_last_action": True}


def _shimmed(package: str):
    """Import `package` through the shim folder, as the README's PYTHONPATH line does."""
    mine = lambda k: k == package or k.startswith(package + ".")  # noqa: E731
    saved = {k: m for k, m in sys.modules.items() if mine(k)}
    for k in saved:
        del sys.modules[k]
    sys.path.insert(0, smac_shim_path())
    try:
        yield importlib.import_module(package + ".env")
    finally:
        sys.path.remove(smac_shim_path())
        for k in [k for k in sys.modules if mine(k)]:
            del sys.modules[k]
        sys.modules.update(saved)


@pytest.fixture
def shim_smac():
    yield from _shimmed("smac")


@pytest.fixture
def shim_smacv2():
    yield from _shimmed("smacv2")


def test_shim_is_smacs_import_path(shim_smac):
    assert shim_smac.StarCraft2Env is StarCraft2Env
    base = importlib.import_module("smac.env.multiagentenv").MultiAgentEnv
    assert base is shim_smac.MultiAgentEnv and issubclass(StarCraft2Env, base)


def run_episode(env, rng, stats):
    """PyMARL's EpisodeRunner.run: getters before each step and after the terminal one,
    actions as a torch LongTensor, the last info summed into `stats`."""
    env.reset()
    terminated, ret, t, batch = False, 0.0, 0, []
    while not terminated:
        pre = {"state": [env.get_state()], "avail_actions": [env.get_avail_actions()],
               "obs": [env.get_obs()]}  # fmt: skip
        avail = torch.tensor(pre["avail_actions"][0], dtype=torch.float32)
        actions = (avail * torch.rand(avail.shape, generator=rng)).argmax(-1).long()[None]
        reward, terminated, env_info = env.step(actions[0])
        ret += reward
        batch.append((pre, actions, reward, terminated != env_info.get("episode_limit", False)))
        t += 1
    last = {"state": [env.get_state()], "avail_actions": [env.get_avail_actions()],
            "obs": [env.get_obs()]}  # fmt: skip
    stats.update({k: stats.get(k, 0) + env_info.get(k, 0) for k in set(stats) | set(env_info)})
    stats["n_episodes"] = 1 + stats.get("n_episodes", 0)
    stats["ep_length"] = t + stats.get("ep_length", 0)
    return batch, last, ret


@pytest.mark.parametrize(("env_args", "state"), [(EPYMARL_SC2, 21), (PYMARL_SC2, 48)])
def test_pymarl_style_loop_with_shipped_sc2_config(shim_smac, env_args, state):
    # EPyMARL's SMACWrapper: StarCraft2Env(map_name=..., seed=..., **rest), then seed(seed).
    kwargs = {k: v for k, v in env_args.items() if k not in ("map_name", "seed")}
    env = shim_smac.StarCraft2Env(map_name=env_args["map_name"], seed=3, **kwargs)
    env.seed(3)
    info = env.get_env_info()
    assert (info["n_agents"], info["n_actions"], info["obs_shape"]) == (3, 9, 30)
    assert info["state_shape"] == state and info["episode_limit"] == 60
    rng, stats = torch.Generator().manual_seed(0), {}
    for _ in range(4):
        batch, last, ret = run_episode(env, rng, stats)
        t = len(batch)
        obs = torch.tensor(np.array([b[0]["obs"][0] for b in batch] + [last["obs"][0]]))
        states = torch.tensor(np.array([b[0]["state"][0] for b in batch] + [last["state"][0]]))
        assert obs.shape == (t + 1, 3, 30) and states.shape == (t + 1, state)
        assert torch.isfinite(obs).all()
        assert [b[3] for b in batch] == [False] * (t - 1) + [True]  # no timeouts at 60 steps
        dead = np.array(last["avail_actions"][0])[:, 0] == 1
        assert (obs[-1][torch.from_numpy(dead)] == 0).all()
        assert 0 <= ret <= 20 + 1e-4
    s = env.get_stats()
    assert stats["n_episodes"] == 4 == s["battles_game"]
    assert stats["battle_won"] == s["battles_won"]
    assert 0 <= stats["dead_enemies"] <= 12 and stats["dead_allies"] <= 12
    assert set(stats) == {"battle_won", "dead_allies", "dead_enemies", "n_episodes", "ep_length"}
    env.close()


def test_randomised_scenario_through_the_shim(shim_smac):
    kwargs = {k: v for k, v in PYMARL_SC2.items() if k not in ("map_name", "seed")}
    env = shim_smac.StarCraft2Env(map_name="zerg_5_vs_5", seed=0, **kwargs)
    assert (env.get_obs_size(), env.get_state_size(), env.get_total_actions()) == (82, 120, 11)
    rng, stats = torch.Generator().manual_seed(0), {}
    for _ in range(3):
        run_episode(env, rng, stats)
    assert stats["n_episodes"] == 3


# env_args of EPyMARL's smacv2_configs/protoss_5_vs_5.yaml (SMACv2's own sc2_gen_protoss).
SMACV2_PROTOSS_5 = {
    **{k: v for k, v in PYMARL_SC2.items() if k not in ("seed", "heuristic_rest")},
    "map_name": "10gen_protoss", "state_last_action": True, "conic_fov": False,
    "use_unit_ranges": True, "min_attack_range": 2, "obs_own_pos": True, "num_fov_actions": 12,
    "capability_config": {
        "n_units": 5, "n_enemies": 5,
        "team_gen": {"dist_type": "weighted_teams", "unit_types": ["stalker", "zealot", "colossus"],
                     "weights": [0.45, 0.45, 0.1], "observe": True},
        "start_positions": {"dist_type": "surrounded_and_reflect", "p": 0.5, "map_x": 32,
                            "map_y": 32},
    },
}  # fmt: skip


def test_smacv2_capability_wrapper_through_the_shim(shim_smacv2):
    wrapper = importlib.import_module("smacv2.env.starcraft2.wrapper")
    env = wrapper.StarCraftCapabilityEnvWrapper(**SMACV2_PROTOSS_5)
    info = env.get_env_info()
    assert (info["obs_shape"], info["state_shape"], info["n_actions"]) == (92, 130, 11)
    assert info["cap_shape"] == 3 and info["episode_limit"] == 200
    ref = StarCraft2Env(map_name="protoss_5_vs_5", seed=4)  # the same scenario, by name
    env.seed(4)
    np.testing.assert_array_equal(env.reset()[1], ref.reset()[1])
    caps = env.get_capabilities().reshape(5, 3)
    assert (caps.sum(1) == 1).all() and (caps == np.array(env.get_obs())[:, -3:]).all()
    rng, stats = torch.Generator().manual_seed(0), {}
    for _ in range(2):
        run_episode(env, rng, stats)
    assert stats["n_episodes"] == 2


@pytest.mark.parametrize(
    ("change", "word"),
    [
        ({"conic_fov": True}, "conic_fov"),
        ({"prob_obs_enemy": 0.0}, "prob_obs_enemy"),
        ({"map_name": "10gen_protoss_big"}, "10gen_protoss"),
        ({"capability_config": {"n_units": 5, "attack": {}}}, "capability_config.attack"),
        ({"capability_config": {"n_units": 5, "team_gen": {"dist_type": "fixed"}}},
         "weighted_teams"),
    ],
)  # fmt: skip
def test_smacv2_options_skirmish_lacks_are_named(shim_smacv2, change, word):
    wrapper = importlib.import_module("smacv2.env.starcraft2.wrapper")
    with pytest.raises(EnvError, match=word):
        wrapper.StarCraftCapabilityEnvWrapper(**{**SMACV2_PROTOSS_5, **change})

"""The SMAC adapter, with a skirmish env standing in for oxwhirl's StarCraft2Env."""

import numpy as np
import pytest

from actors.envs.base import EnvError
from actors.envs.registry import make_env
from actors.envs.skirmish import SkirmishEnv, builtin_map, make_skirmish
from actors.envs.skirmish.spec import parse_map
from actors.envs.smac_backend import SmacEnv, load_starcraft2env

FAR_APART = parse_map(
    "far_apart",
    {
        "episode_limit": 4,
        "allies": [{"type": "marine", "count": 2, "at": [2, 16]}],
        "enemies": [{"type": "marine", "count": 2, "at": [30, 16]}],
    },
    "<test>",
)


class ListSmac(SkirmishEnv):
    """SMAC-API stand-in that answers in lists like StarCraft2Env and reports a timeout
    without `episode_limit` (SMAC's default continuing_episode=False)."""

    def __init__(self, map_name, seed=None, **kwargs):
        spec = FAR_APART if map_name == "far_apart" else builtin_map(map_name)
        super().__init__(spec, seed=seed)

    def reset(self):
        obs, state = super().reset()
        return list(obs), list(state)

    def step(self, actions):
        assert isinstance(actions, list)
        r, term, info = super().step(actions)
        info = {k: v for k, v in info.items() if k != "episode_limit"}
        return r, term, info

    def get_avail_actions(self):
        return [list(a) for a in super().get_avail_actions()]


def test_without_smac_the_error_says_how_to_install():
    try:
        load_starcraft2env()
    except EnvError as e:
        msg = str(e)
        assert "github.com/oxwhirl/smac" in msg and "SC2PATH" in msg and "SMAC3" in msg
    else:
        pytest.skip("oxwhirl SMAC is installed here")
    with pytest.raises(EnvError, match="StarCraft II"):
        make_env("smac/3m", seed=0)


def test_adapter_matches_the_wrapped_env():
    env = SmacEnv("3m", seed=4, env_cls=ListSmac)
    ref = make_skirmish(4, map_name="3m")
    info = env.get_env_info()
    assert info["n_enemies"] == 3 and info["has_wins"] is True
    assert (info["obs_shape"], info["state_shape"], info["n_actions"]) == (30, 48, 9)
    obs, state = env.reset()
    ref_obs, ref_state = ref.reset()
    assert obs.dtype == np.float32 and isinstance(obs, np.ndarray)
    np.testing.assert_array_equal(obs, ref_obs)
    np.testing.assert_array_equal(state, ref_state)
    for _ in range(5):
        a = [int(np.flatnonzero(row)[-1]) for row in env.get_avail_actions()]
        r, term, info = env.step(a)
        r2, term2, _ = ref.step(a)
        assert (r, term) == (pytest.approx(r2), term2)
        assert info["episode_limit"] is False


def test_adapter_checks_actions_and_flags_timeouts():
    env = SmacEnv("3m", seed=0, env_cls=ListSmac)
    env.reset()
    with pytest.raises(EnvError, match="agent 0 cannot take action 0"):
        env.step([0, 1, 1])
    env = SmacEnv("far_apart", seed=0, env_cls=ListSmac)
    env.reset()
    infos = [env.step([1, 1]) for _ in range(4)]
    assert [term for _, term, _ in infos] == [False, False, False, True]
    assert [i["episode_limit"] for _, _, i in infos] == [False, False, False, True]
    assert infos[-1][2]["battle_won"] is False


def test_adapter_takes_skirmish_starcraft2env_like_oxwhirls(tmp_path):
    """skirmish's StarCraft2Env answers the adapter as oxwhirl's does (lists, no
    episode_limit in the info without continuing_episode); the adapter flags the timeout."""
    from actors.envs.skirmish import StarCraft2Env

    env = SmacEnv("3m", seed=4, env_cls=StarCraft2Env)
    ref = make_skirmish(4, map_name="3m")
    np.testing.assert_array_equal(env.reset()[1], ref.reset()[1])
    path = tmp_path / "far.yaml"
    path.write_text(
        "episode_limit: 3\n"
        "allies: [{type: marine, count: 1, at: [2, 16]}]\n"
        "enemies: [{type: marine, count: 1, at: [30, 16]}]\n"
    )
    env = SmacEnv(str(path), seed=0, env_cls=StarCraft2Env)
    env.reset()
    infos = [env.step([1])[2] for _ in range(3)]
    assert [i["episode_limit"] for i in infos] == [False, False, True]

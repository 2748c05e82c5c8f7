"""Every payoff and transition of the two matrix games."""

import numpy as np
import pytest

from actors.envs import EnvError, env_ids, make_env

TWO_STEP = {  # (step-1 action of agent 0, agent 1) -> payoff matrix of step 2
    (0, 0): [[7, 7], [7, 7]],
    (0, 1): [[7, 7], [7, 7]],
    (1, 0): [[0, 1], [1, 8]],
    (1, 1): [[0, 1], [1, 8]],
}
FOUR_GAME = {
    (0, 0): [[7, 7], [7, 7]],
    (0, 1): [[2, 0], [0, 2]],
    (1, 1): [[0, 1], [1, 8]],
    (1, 0): [[2, 2], [2, 2]],
}
CASES = [("matrix/two_step", TWO_STEP), ("matrix/four_game", FOUR_GAME)]


@pytest.mark.parametrize("env_id, table", CASES)
def test_every_payoff_and_transition(env_id, table):
    env = make_env(env_id, seed=0)
    stages = set()
    for first, payoff in table.items():
        for a0 in range(2):
            for a1 in range(2):
                obs, state = env.reset()
                assert state.tolist()[0] == 1.0 and state.sum() == 1.0  # start stage
                np.testing.assert_array_equal(obs, np.stack([state, state]))
                r1, done1, info1 = env.step(np.array(first))
                assert (r1, done1, info1["episode_limit"]) == (0.0, False, False)
                stages.add(int(np.argmax(env.get_state())))
                r2, done2, _ = env.step(np.array([a0, a1]))
                assert r2 == payoff[a0][a1] and done2
    # distinct step-1 games lead to distinct observed stages
    assert len(stages) == len({str(v) for v in table.values()})


def test_four_game_payoffs_are_configurable_and_validated():
    payoffs = {
        "00": [[1, 1], [1, 1]],
        "01": [[0, 0], [0, 0]],
        "10": [[0, 0], [0, 0]],
        "11": [[0, 0], [0, 9]],
    }
    env = make_env("matrix/four_game", payoffs=payoffs)
    env.reset()
    env.step([1, 1])
    assert env.step([1, 1])[0] == 9.0
    assert env.optimal_return == 9.0
    with pytest.raises(EnvError, match="payoffs"):
        make_env("matrix/four_game", payoffs={"00": [[1, 1], [1, 1]]})


def test_env_info_and_errors():
    info = make_env("matrix/four_game").get_env_info()
    assert info | {} == {
        **info,
        "n_agents": 2,
        "n_actions": 2,
        "obs_shape": 5,
        "state_shape": 5,
        "episode_limit": 2,
    }
    assert make_env("matrix/two_step").get_env_info()["obs_shape"] == 3
    with pytest.raises(EnvError, match=r"valid envs: .*matrix/four_game"):
        make_env("matrix/nope")
    with pytest.raises(EnvError, match="no argument 'bogus'"):
        make_env("matrix/two_step", bogus=1)
    env = make_env("matrix/two_step")
    env.reset()
    with pytest.raises(EnvError, match="agent 1 cannot take action 5"):
        env.step([0, 5])
    assert "matrix/two_step" in env_ids()

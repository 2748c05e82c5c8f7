"""One fast smoke test per registered algorithm, plus padding and ensemble properties."""

import numpy as np
import pytest
import torch

from actors.envs import make_vec_env
from actors.policy import ExplorationConfig
from actors.rollout import RolloutWorker
from buffer_service.episode import EpisodeBatch
from learner.networks import AgentNet
from learner.registry import ALGOS, get_algo


def _episodes(env_id: str, n: int, seed: int = 0):
    venv = make_vec_env(env_id, n, seed=seed)
    info = venv.info
    net = AgentNet(1, info.obs_shape + info.n_actions + info.n_agents, info.n_actions)
    worker = RolloutWorker(venv, net, "q", ExplorationConfig(epsilon_anneal_time=1), seed=seed)
    return info, worker.collect(n, t_env=0)


@pytest.mark.parametrize("name", sorted(ALGOS))
def test_smoke_every_algorithm(name):
    torch.manual_seed(0)
    info, episodes = _episodes("matrix/four_game", 4)
    spec = ALGOS[name]
    learner = spec.build(spec.config_cls(), info.schema(), 1, "cpu")
    before = learner.get_weights()
    batch = EpisodeBatch.from_episodes(episodes)
    for _ in range(3):
        metrics = learner.step(batch)
    assert metrics and all(np.isfinite(v) for v in metrics.values())
    after = learner.get_weights()
    assert after.version == 3 > before.version
    changed = [not np.allclose(before.arrays[k], after.arrays[k]) for k in before.arrays]
    assert any(changed)
    state = learner.state_dict()
    clone = spec.build(spec.config_cls(), info.schema(), 1, "cpu")
    clone.load_state_dict(state)
    assert clone.updates == 3
    for k, v in clone.get_weights().arrays.items():
        np.testing.assert_array_equal(v, after.arrays[k])


@pytest.mark.parametrize("name", sorted(ALGOS))
def test_padding_is_ignored(name):
    """Padding a batch with extra empty steps does not change the update."""
    info, episodes = _episodes("matrix/two_step", 3)
    batch = EpisodeBatch.from_episodes(episodes)
    padded = batch.pad_to(batch.max_t + 3)
    results = []
    for b in (batch, padded):
        torch.manual_seed(1)
        spec = ALGOS[name]
        learner = spec.build(spec.config_cls(), info.schema(), 1, "cpu")
        learner.step(b)
        results.append(learner.get_weights().arrays)
    for k in results[0]:
        np.testing.assert_allclose(results[0][k], results[1][k], atol=1e-6)


def test_seed_batched_update_equals_separate_updates():
    """Member k of an E=2 learner follows the update an E=1 learner with member k's weights
    would follow on member k's batch (Adam is elementwise, clipping per member)."""
    info, eps_a = _episodes("matrix/four_game", 4, seed=0)
    _, eps_b = _episodes("matrix/four_game", 4, seed=1)
    ba, bb = EpisodeBatch.from_episodes(eps_a), EpisodeBatch.from_episodes(eps_b)
    spec = get_algo("rdn")
    torch.manual_seed(0)
    pair = spec.build(spec.config_cls(), info.schema(), 2, "cpu")
    init = {k: v.clone() for k, v in pair.state_dict()["agent"].items()}
    critic_init = {k: v.clone() for k, v in pair.state_dict()["critic"].items()}
    pair.step(EpisodeBatch.stack([ba, bb]))
    for member, batch in ((0, ba), (1, bb)):
        single = spec.build(spec.config_cls(), info.schema(), 1, "cpu")
        single.agent.load_state_dict({k: v[member : member + 1] for k, v in init.items()})
        single.critic.load_state_dict({k: v[member : member + 1] for k, v in critic_init.items()})
        single.target_critic.module.load_state_dict(single.critic.state_dict())
        single.step(batch)
        for k, v in single.agent.state_dict().items():
            torch.testing.assert_close(
                v[0], pair.agent.state_dict()[k][member], atol=1e-5, rtol=1e-4
            )


def test_unknown_algorithm_lists_valid_names():
    with pytest.raises(
        ValueError,
        match="valid algorithms: cac, coma, ecac, emcac, iql, mcac, qmix, qmix_ns, rdn, vdn",
    ):
        get_algo("dqn")

"""What an RDN critic learned on a matrix game: for every reachable state and joint action, the
critic's value and each agent's LRP share of it, next to the agents' own Q-values.

This is the evidence to look at when RDN misses the optimum: whether the critic ranks the joint
actions right, and whether the relevance split hands the right agent the credit.
"""

from __future__ import annotations

import itertools

import numpy as np
import torch

from actors.envs.registry import make_env
from buffer_service.episode import Episode, EpisodeBatch
from learner.batch import TensorBatch, agent_inputs, obs_history
from learner.lrp import agent_relevance, lrp_epsilon
from learner.networks import unroll
from learner.rdn import RDNLearner


def _episode(
    env_id: str, env_args: dict, first: tuple[int, int], second: tuple[int, int]
) -> Episode:
    env = make_env(env_id, seed=0, **env_args)
    obs, state, avail, rewards = [], [], [], []
    env.reset()
    for joint in (first, second):
        obs.append(env.get_obs())
        state.append(env.get_state())
        avail.append(env.get_avail_actions())
        rewards.append(env.step(np.array(joint))[0])
    obs.append(env.get_obs())
    state.append(env.get_state())
    avail.append(env.get_avail_actions())
    return Episode(
        obs=np.asarray(obs, np.float32),
        state=np.asarray(state, np.float32),
        avail_actions=np.asarray(avail, np.uint8),
        actions=np.asarray([first, second], np.int64),
        reward=np.asarray(rewards, np.float32),
        terminated=np.array([False, True]),
        filled=np.ones(2, bool),
    )


def diagnose(learner: RDNLearner, env_id: str, env_args: dict) -> list[dict]:
    """Per ensemble member: critic values, relevance shares and agent Q-values per state.

    Returns a list (one entry per member) of {"step1": [...], "step2": {first: [...]},
    "agent_q_step1": [[Q_0(0), Q_0(1)], [Q_1(0), Q_1(1)]]}.
    """
    joints = list(itertools.product(range(2), repeat=2))
    paths = [(f, s) for f in joints for s in joints]
    batch = EpisodeBatch.from_episodes([_episode(env_id, env_args, f, s) for f, s in paths])
    stacked = EpisodeBatch.stack([batch] * learner.n_ensemble)
    tb = TensorBatch.from_episodes(stacked)
    e, b, t, n = tb.shape
    with torch.no_grad():
        hist = obs_history(tb.obs, learner.cfg.obs_window)
        x = learner.critic_inputs(hist[:, :, :-1], tb.actions)
        rel, q = lrp_epsilon(learner.critic, x, learner.cfg.lrp_eps, learner.cfg.lrp_rule)
        shares = agent_relevance(rel, n).view(e, b, t, n)
        q = q.view(e, b, t)
        agent_q = unroll(learner.agent, agent_inputs(tb.obs, tb.actions, learner.info.n_actions))
    out = []
    for m in range(e):
        step1 = []
        step2: dict[str, list] = {}
        for k, (first, second) in enumerate(paths):
            if second == (0, 0):
                step1.append(_cell(first, q[m, k, 0], shares[m, k, 0]))
            step2.setdefault(f"{first[0]}{first[1]}", []).append(
                _cell(second, q[m, k, 1], shares[m, k, 1])
            )
        out.append(
            {
                "step1": step1,
                "step2": step2,
                "agent_q_step1": agent_q[m, 0, 0].round(decimals=3).tolist(),
            }
        )
    return out


def _cell(joint: tuple[int, int], q: torch.Tensor, share: torch.Tensor) -> dict:
    return {
        "joint_action": list(joint),
        "critic_q": round(float(q), 3),
        "relevance": [round(float(s), 3) for s in share],
    }

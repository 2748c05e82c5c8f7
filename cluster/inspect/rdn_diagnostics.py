"""What an RDN critic learned on a matrix game: for every reachable state and joint action, the
critic's value and each agent's LRP share of it, next to the agents' own Q-values.

This is the evidence to look at when RDN misses the optimum: whether the critic ranks the joint
actions right, and whether the relevance split hands the right agent the credit.
"""

from __future__ import annotations

import itertools

import numpy as np
import torch
from torch.nn import functional as F

from actors.envs.registry import make_env
from buffer_service.episode import Episode, EpisodeBatch
from learner.batch import TensorBatch, agent_inputs
from learner.critic_inputs import obs_history
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
        shares, q = learner.shares(hist[:, :, :-1], tb.actions)
        shares = shares.view(e, b, t, n)
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


def own_action_credit(learner: RDNLearner, batch: EpisodeBatch, seed: int = 0) -> dict:
    """How much each agent's LRP target moves with its own action, against how much the
    critic's value moves, and against how much the target moves with its own observations.

    For every real transition and agent i (alive or not), agent i's action is replaced by each
    other action available to it, everything else fixed: dq = Q_c(x') - Q_c(x) and
    dr = R_i(x') - R_i(x). Separately agent i's observation window is replaced by agent i's
    window from another, random transition of the batch (its action kept): do = R_i(x'') - R_i(x).
    A split that credits agents for their own actions has dr close to dq.

    Returns means over members, transitions and agents: `mean_abs_dq`, `mean_abs_dr`,
    `mean_abs_dr_obs`, `slope_dr_on_dq` (least squares), `sign_agreement` (share of swaps with
    |dq| > 0.01 where dr has dq's sign), `argmax_agreement` (share of (transition, agent) where
    the action maximising R_i is the one maximising Q_c), `agent_argmax_agreement` (the same for
    the agent network's own greedy action: does the agent act as the critic would have it?),
    `swaps`.
    """
    tb = TensorBatch.from_episodes(batch)
    e, b, t, n = tb.shape
    a_n = learner.info.n_actions
    cfg = learner.cfg
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        hist = obs_history(tb.obs, cfg.obs_window)[:, :, :-1]  # [E, B, T, N, W*O]
        avail = tb.avail[:, :, :-1]
        real = tb.mask.bool()

        def split(h: torch.Tensor, acts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            shares, q = learner.shares(h, acts)
            return shares.view(e, b, t, n), q.view(e, b, t)

        r0, q0 = split(hist, tb.actions)
        agent_q = unroll(learner.agent, agent_inputs(tb.obs, tb.actions, a_n))[:, :, :-1]
        dq_all, dr_all, agree_arg, agree_agent = [], [], [], []
        for i in range(n):
            rs, qs = [], []
            for a in range(a_n):
                acts = tb.actions.clone()
                acts[..., i] = a
                r, q = split(hist, acts)
                rs.append(r[..., i])
                qs.append(q)
            rs_t, qs_t = torch.stack(rs, -1), torch.stack(qs, -1)  # [E, B, T, A]
            ok = avail[..., i, :] & real.unsqueeze(-1)
            own = F.one_hot(tb.actions[..., i], a_n).bool()
            swap = ok & ~own
            dq_all.append((qs_t - q0.unsqueeze(-1))[swap])
            dr_all.append((rs_t - r0[..., i].unsqueeze(-1))[swap])
            choosable = ok.sum(-1) > 1
            best_q = qs_t.masked_fill(~ok, -1e10).argmax(-1)
            best_r = rs_t.masked_fill(~ok, -1e10).argmax(-1)
            agree_arg.append((best_q == best_r)[choosable].float())
            best_agent = agent_q[..., i, :].masked_fill(~ok, -1e10).argmax(-1)
            agree_agent.append((best_q == best_agent)[choosable].float())
        dq, dr = torch.cat(dq_all), torch.cat(dr_all)
        flat = hist.dense().reshape(e, b * t, n, -1)
        perm = torch.randperm(b * t, generator=gen)
        do_all = []
        for i in range(n):
            h2 = flat.clone()
            h2[:, :, i] = flat[:, perm, i]
            r2, _ = split(h2.view(hist.shape), tb.actions)
            do_all.append((r2[..., i] - r0[..., i])[real])
        do = torch.cat(do_all)
    big = dq.abs() > 0.01
    slope = float((dq * dr).sum() / (dq * dq).sum().clamp_min(1e-12))
    return {
        "mean_abs_dq": float(dq.abs().mean()),
        "mean_abs_dr": float(dr.abs().mean()),
        "mean_abs_dr_obs": float(do.abs().mean()),
        "slope_dr_on_dq": slope,
        "sign_agreement": float((torch.sign(dr[big]) == torch.sign(dq[big])).float().mean())
        if big.any()
        else None,
        "argmax_agreement": float(torch.cat(agree_arg).mean()),
        "agent_argmax_agreement": float(torch.cat(agree_agent).mean()),
        "swaps": int(dq.numel()),
    }

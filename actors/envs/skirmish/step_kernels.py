"""Numba kernels at the edges of an agent step of the skirmish simulator: putting battles at
their start (`reset_battles`), turning the agents' actions into orders (`set_orders`) and the
step's outcome (`outcome`: reward, termination, win). The sub-steps in between are
`kernels.advance`; the data layout is described there."""

from __future__ import annotations

import numpy as np
from numba import njit

from actors.envs.skirmish.kernels import (
    ATTACK,
    CD,
    EN,
    HEALER,
    HP,
    HP_MAX,
    IDLE,
    KIND,
    LAST_TGT,
    MDIR,
    MOVE,
    ORDER,
    OTGT,
    REM,
    SH,
    SH_MAX,
    SINCE,
    X,
    Y,
)


@njit(cache=True)
def reset_battles(envs, draws, jitter, rid, start_pos, goal, team, uf, energy_start, f, g, alive,
                  way):  # fmt: skip
    """Put battles `envs` at their start (their roster's start_pos [R, U, 2], goal [R, 2]).
    draws [k, 4 + 2U] uniform [0, 1) per env: each side's formation shift (jitter[0]) then
    a per-unit offset (jitter[1])."""
    U = alive.shape[1]
    for k in range(envs.shape[0]):
        m = envs[k]
        d = draws[k]
        r = rid[m]
        for u in range(U):
            side = team[u]
            dx = (2 * d[2 * side] - 1) * jitter[0] + (2 * d[4 + 2 * u] - 1) * jitter[1]
            dy = (2 * d[2 * side + 1] - 1) * jitter[0] + (2 * d[5 + 2 * u] - 1) * jitter[1]
            f[m, X, u] = min(max(start_pos[r, u, 0] + dx, 0.0), jitter[2])
            f[m, Y, u] = min(max(start_pos[r, u, 1] + dy, 0.0), jitter[3])
            f[m, HP, u] = uf[r, u, HP_MAX]
            f[m, SH, u] = uf[r, u, SH_MAX]
            f[m, CD, u] = 0.0
            f[m, EN, u] = energy_start[r, u]
            f[m, SINCE, u] = 0.0
            f[m, REM, u] = 0.0
            alive[m, u] = True
            g[m, :, u] = 0
            g[m, OTGT, u] = -1
            g[m, LAST_TGT, u] = -1
        way[m, 0] = goal[r, 0] + (2 * d[0] - 1) * jitter[0]
        way[m, 1] = goal[r, 1] + (2 * d[1] - 1) * jitter[0]


@njit(cache=True)
def set_orders(acts, active, avail, N, rid, agent_healer, move_amount, f, g, last_action):
    """Check every active agent's action against `avail` and turn actions into orders
    (agent_healer [R, N]: a healer's target index is an ally's; a move order goes
    `move_amount` far).

    Returns -1, or m * N + i of the first unavailable action (then nothing is changed).
    """
    M, A = acts.shape[0], avail.shape[2]
    for m in range(M):
        if not active[m]:
            continue
        for i in range(N):
            a = acts[m, i]
            if a < 0 or a >= A or avail[m, i, a] == 0:
                return m * N + i
    for m in range(M):
        if not active[m]:
            continue
        healer = agent_healer[rid[m]]
        for i in range(N):
            a = acts[m, i]
            g[m, ORDER, i] = ATTACK if a >= 6 else (MOVE if a >= 2 else IDLE)
            g[m, OTGT, i] = -1 if a < 6 else (a - 6 if healer[i] else N + a - 6)
            g[m, MDIR, i] = a if 2 <= a <= 5 else 0
            f[m, REM, i] = move_amount if 2 <= a <= 5 else 0.0
            last_action[m, i, :] = 0.0
            last_action[m, i, a] = 1.0
    return -1


@njit(cache=True)
def outcome(active, t, N, limit, rp, scale, rid, uis, f, alive, before, reward, term, won,
            timeout):  # fmt: skip
    """SMAC's reward and end of episode per battle after a step.

    rp = (death value, win reward, defeat reward, reward_scale 0/1, only positive 0/1,
    negative scale, sparse 0/1); scale [R] = max_reward / reward_scale_rate per roster.
    """
    M, U = alive.shape
    for m in range(M):
        reward[m], won[m], timeout[m], term[m] = 0.0, False, False, True
        if not active[m]:
            continue
        ui = uis[rid[m]]
        hs = np.zeros(2)
        dead = np.zeros(2)
        fight = np.zeros(2, np.bool_)
        for u in range(U):
            side = 0 if u >= N else 1
            hs[side] += f[m, HP, u] + f[m, SH, u]
            if not alive[m, u]:
                dead[side] += 1.0
            elif ui[u, KIND] != HEALER:
                fight[side] = True
        r = before[m, 0] - hs[0] + rp[0] * (dead[0] - before[m, 2])
        if rp[6] > 0:
            r = 0.0
        elif rp[4] > 0:
            r = abs(r)
        else:
            r -= rp[5] * (before[m, 1] - hs[1] + rp[0] * (dead[1] - before[m, 3]))
        w = fight[1] and not fight[0]
        ended = not (fight[0] and fight[1])
        if w:
            r = 1.0 if rp[6] > 0 else r + rp[1]
        elif fight[0] and ended:
            r = -1.0 if rp[6] > 0 else r + rp[2]
        to = not ended and t[m] >= limit
        if rp[3] > 0:
            r /= scale[rid[m]]
        reward[m], won[m], timeout[m], term[m] = r, w, to, ended or to

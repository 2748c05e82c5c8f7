"""Scripted (privileged) policies for sanity tests and map comparisons, batched over envs.

Each policy is `policy(venv, rng) -> actions [M, N]` for a `SkirmishVecEnv` and always picks
available actions. They read the simulator's state directly (they are baselines, not agents).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from actors.envs.skirmish.env import SkirmishVecEnv
from actors.envs.skirmish.spec import KINDS

Policy = Callable[[SkirmishVecEnv, np.random.Generator], np.ndarray]
NORTH, SOUTH, EAST, WEST = 2, 3, 4, 5


def random_policy(venv: SkirmishVecEnv, rng: np.random.Generator) -> np.ndarray:
    """Uniform over each agent's available actions."""
    avail = venv.get_avail_actions()
    return (avail * rng.random(avail.shape)).argmax(-1)


def _toward(venv: SkirmishVecEnv, sign: float) -> np.ndarray:
    """Move action [M, N] toward (sign=+1) or away from (-1) the nearest living enemy,
    along the larger axis; falls back to stop when that move is unavailable."""
    b, N = venv.battle, venv.st.N
    dx, dy, dist = venv.pairwise()
    d = np.where(b.alive[:, None, N:], dist[:, :N, N:], np.inf)
    j = d.argmin(-1)
    tx = np.take_along_axis(dx[:, :N, N:], j[..., None], 2)[..., 0] * sign
    ty = np.take_along_axis(dy[:, :N, N:], j[..., None], 2)[..., 0] * sign
    horiz = np.abs(tx) >= np.abs(ty)
    move = np.where(horiz, np.where(tx > 0, EAST, WEST), np.where(ty > 0, NORTH, SOUTH))
    avail = venv.get_avail_actions()
    ok = np.take_along_axis(avail, move[..., None], 2)[..., 0] > 0
    return np.where(ok, move, 1)


def _attack_or(venv: SkirmishVecEnv, score: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Attack the available enemy with the lowest `score` [M, N, E], else `fallback`."""
    avail = venv.get_avail_actions()
    can = avail[:, :, 6:] > 0
    s = np.where(can, score, np.inf)
    best = s.argmin(-1)
    acts = np.where(can.any(-1), 6 + best, fallback)
    dead = avail[:, :, 0] > 0
    return np.where(dead, 0, acts)


def _advance(venv: SkirmishVecEnv) -> np.ndarray:
    """Move toward the nearest enemy; but before contact (no enemy within shoot range of any
    agent) hold once an enemy is in sight, so the enemy walks into range rather than
    getting the first volley."""
    b, N, ro = venv.battle, venv.st.N, venv.battle.rosters
    _, _, dist = venv.pairwise()
    d = np.where(b.alive[:, None, N:] & b.alive[:, :N, None], dist[:, :N, N:], np.inf)
    sight, shoot = ro.sight[b.rid][..., None], ro.shoot[b.rid][..., None]  # [M, N, 1]
    seen = (d < sight).any(-1)
    contact = (d <= shoot).any((1, 2))
    return np.where(seen & ~contact[:, None], 1, _toward(venv, 1.0))


def focus_fire_policy(venv: SkirmishVecEnv, rng: np.random.Generator) -> np.ndarray:
    """All attack the weakest enemy (health + shield) in range, else advance; ties go to the
    enemy closest to the team as a whole, so that the agents pick the same one."""
    b, N = venv.battle, venv.st.N
    _, _, dist = venv.pairwise()
    d = np.where(b.alive[:, :N, None], dist[:, :N, N:], 0.0).sum(1)  # [M, E]
    weak = (b.hp[:, N:] + b.sh[:, N:]) + 1e-3 * d / max(venv.cfg.sight_range * N, 1.0)
    score = np.broadcast_to(weak[:, None, :], (b.M, N, venv.st.E))
    return _attack_or(venv, score, _advance(venv))


def nearest_policy(venv: SkirmishVecEnv, rng: np.random.Generator) -> np.ndarray:
    """Everyone attacks the nearest enemy in range, else advances."""
    N = venv.st.N
    _, _, dist = venv.pairwise()
    return _attack_or(venv, dist[:, :N, N:], _advance(venv))


def bane_charge_policy(venv: SkirmishVecEnv, rng: np.random.Generator) -> np.ndarray:
    """ "Banelings charge, zerglings step aside" (the dissertation's bane_vs_bane rollout:
    the zerglings move backwards out of the banelings' way): banelings attack the nearest
    enemy; zerglings step back (away from the nearest enemy) while any baneling, ours or the
    enemy's, lives, then attack the nearest enemy. Once no allied zergling lives, the first
    living allied baneling is kept in reserve and steps back too (a win needs a living
    agent, and a baneling dies when it bursts)."""
    b, N = venv.battle, venv.st.N
    bane = b.kind == KINDS.index("baneling")  # [M, U]
    step = ~bane[:, :N] & (b.alive & bane).any(1)[:, None]
    mine = bane[:, :N] & b.alive[:, :N]
    no_lings = ~(~bane[:, :N] & b.alive[:, :N]).any(1)
    first = np.arange(N)[None, :] == mine.argmax(1)[:, None]
    step |= mine & first & no_lings[:, None]
    return _lings_make_way(venv, rng, step, _toward(venv, -1.0))


def bane_aside_policy(venv: SkirmishVecEnv, rng: np.random.Generator) -> np.ndarray:
    """Like bane_charge, but the zerglings step sideways out of the lane from our banelings
    to the enemy (each to the side it stands on) while any of our banelings lives."""
    b, N = venv.battle, venv.st.N
    bane = b.kind == KINDS.index("baneling")
    mine = bane[:, :N] & b.alive[:, :N]
    ours, foes = (
        _centre(b.x[:, :N], b.y[:, :N], mine),
        _centre(b.x[:, N:], b.y[:, N:], b.alive[:, N:]),
    )
    ax, ay = foes[0] - ours[0], foes[1] - ours[1]  # [M] the lane's direction
    side = np.sign(
        ax[:, None] * (b.y[:, :N] - ours[1][:, None])
        - ay[:, None] * (b.x[:, :N] - ours[0][:, None])
    )
    side = np.where(side == 0, 1.0, side)
    px, py = -ay[:, None] * side, ax[:, None] * side
    move = np.where(
        np.abs(px) >= np.abs(py), np.where(px > 0, EAST, WEST), np.where(py > 0, NORTH, SOUTH)
    )
    ok = np.take_along_axis(venv.get_avail_actions(), move[..., None], 2)[..., 0] > 0
    step = ~bane[:, :N] & mine.any(1)[:, None]
    return _lings_make_way(venv, rng, step, np.where(ok, move, 1))


def _centre(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean position [M] of the units where `w` [M, K]."""
    n = np.maximum(w.sum(1), 1)
    return (x * w).sum(1) / n, (y * w).sum(1) / n


def _lings_make_way(venv, rng, step: np.ndarray, move: np.ndarray) -> np.ndarray:
    """Agents where `step` [M, N] take `move`; the others attack the nearest enemy."""
    acts = np.where(step, move, nearest_policy(venv, rng))
    dead = venv.get_avail_actions()[:, :, 0] > 0
    return np.where(dead, 0, acts)


POLICIES: dict[str, Policy] = {
    "random": random_policy,
    "focus_fire": focus_fire_policy,
    "nearest": nearest_policy,
    "bane_charge": bane_charge_policy,
    "bane_aside": bane_aside_policy,
}


def evaluate(venv: SkirmishVecEnv, policy: Policy, episodes: int, seed: int = 0) -> dict:
    """Play `episodes` episodes (in rounds of M) and return win rate, timeout rate (episodes
    cut by the time limit, which count as losses), mean return and mean length."""
    rng = np.random.default_rng(seed)
    wins, timeouts, returns, lengths = [], [], [], []
    while len(wins) < episodes:
        venv.reset()
        active = np.ones(venv.num_envs, bool)
        ret = np.zeros(venv.num_envs)
        won = np.zeros(venv.num_envs, bool)
        cut = np.zeros(venv.num_envs, bool)
        t = np.zeros(venv.num_envs, np.int64)
        while active.any():
            r, term, infos = venv.step(policy(venv, rng), active)
            ret += r
            t += active
            for k in np.flatnonzero(active & term):
                won[k] = infos[k]["battle_won"]
                cut[k] = infos[k]["episode_limit"]
            active &= ~term
        wins += won.tolist()
        timeouts += cut.tolist()
        returns += ret.tolist()
        lengths += t.tolist()
    return {
        "episodes": episodes,
        "win_rate": float(np.mean(wins[:episodes])),
        "timeout_rate": float(np.mean(timeouts[:episodes])),
        "mean_return": float(np.mean(returns[:episodes])),
        "mean_length": float(np.mean(lengths[:episodes])),
    }

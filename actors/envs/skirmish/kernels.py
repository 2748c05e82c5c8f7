"""Numba kernels of the skirmish dynamics: one call advances every active battle by all the
sub-steps of one agent step (no per-step NumPy temporaries, no Python per unit).

Data layout (built by `sim.Statics` / `sim.Battle`; unit u < N is agent u, else enemy u - N):

* Per roster r (battle m uses r = rid[m]; `sim.Rosters`): uf [R, U, N_UF] float per-unit
  stats (columns HP_MAX ... SPLASH_W; WAY_DX/DY: an enemy's offset from its group's centre
  at the start, kept on the way), ui [R, U, N_UI] int (TEAM, KIND, HEALABLE, THREAT), hit
  [R, 2, U, U] damage of one attack of i on j to (health after armour, shields), can_hit
  [R, U, U] (foe and a weapon that reaches it: ground / air), collide [R, U, U]. The
  per-sub-step helpers take one roster's 2-D slices. par [N_PAR] scalars (P_LOOPS ...).
* f [M, N_F, U] float state (X, Y, HP, SH, CD, EN, SINCE, REM: distance left of a move
  order, which ends `move_amount` away as in SMAC), g [M, N_G, U] int state (ORDER,
  OTGT: target unit index, MDIR: move action 2-5, ARRIVED, LAST_TGT), alive [M, U],
  way [M, 2] the point the scripted enemy attack-moves to (the agents' spawn).

Behaviour per sub-step (SMAC on SC2): agents do what they were ordered and nothing else (SMAC
sets the allies' acquire level to passive, so a stopped or moving agent never fires); a
medivac heals its ordered ally or auto-casts on a hurt ally in range. Enemies run SC2's
attack-move: attack the closest agent they can hit within acquire range (units that can fight
before units that cannot), else walk to the agents' spawn and, once there, hunt the closest
agent; like SC2's group move to a far point, each keeps its place in the formation on the
way. Attacks resolve together; a baneling bursts on reaching its target and also when it
is killed (its splash hits only the other side's ground units, as in SC2), so bursts chain.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

RANGED, MELEE, BANE, HEALER, COLOSSUS = range(5)  # spec.KINDS order
IDLE, MOVE, ATTACK = 0, 1, 2
HP_MAX, SH_MAX, RANGE, RADIUS, STEP, CD_LOOPS, EN_MAX, EN_REGEN = range(8)
HEAL, HP_PER_EN, SPLASH_R, SPLASH_LEN, SPLASH_W, WAY_DX, WAY_DY = range(8, 15)
N_UF = 15
TEAM, KIND, HEALABLE, THREAT = range(4)
N_UI = 4
X, Y, HP, SH, CD, EN, SINCE, REM = range(8)
N_F = 8
ORDER, OTGT, MDIR, ARRIVED, LAST_TGT = range(5)
N_G = 5
P_LOOPS, P_MAP_W, P_MAP_H, P_REGEN_DELAY, P_REGEN, P_ACQUIRE, P_ARRIVE, P_DODGE = range(8)
N_PAR = 8
# Movement modes of one sub-step.
M_HOLD, M_CHASE, M_DIR, M_WAY, M_FLEE = 0, 1, 2, 3, 4
SEPARATION_PASSES = 3
_DX = np.array([0.0, 0.0, 0.0, 0.0, 1.0, -1.0])  # actions 2-5: north, south, east, west
_DY = np.array([0.0, 0.0, 1.0, -1.0, 0.0, 0.0])


@njit(cache=True)
def advance(active, n_sub, N, par, rid, ufs, uis, hits, can_hits, collides, f, g, alive, way,
            before):  # fmt: skip
    """Run `n_sub` sub-steps in every active battle; `before` [M, 4] receives each battle's
    (enemy health + shields, ally health + shields, dead enemies, dead allies) beforehand."""
    M, U = alive.shape
    dist = np.zeros((U, U))
    tgt = np.empty(U, np.int64)
    mode = np.empty(U, np.int64)
    fire = np.empty(U, np.bool_)
    boom = np.empty(U, np.bool_)
    dmg = np.zeros((2, U))
    heal = np.zeros(U)
    nx = np.empty(U)
    ny = np.empty(U)
    for m in range(M):
        if not active[m]:
            continue
        r = rid[m]
        uf, ui, hit, can_hit, collide = ufs[r], uis[r], hits[r], can_hits[r], collides[r]
        before[m, :] = 0.0
        for u in range(U):
            side = 0 if u >= N else 1
            before[m, side] += f[m, HP, u] + f[m, SH, u]
            if not alive[m, u]:
                before[m, 2 + side] += 1.0
        for _ in range(n_sub):
            _pairwise(f, m, dist)
            _targets(m, N, par, uf, ui, can_hit, f, g, alive, dist, tgt, mode)
            _fire(m, par, uf, ui, f, alive, dist, tgt, mode, fire)
            _attacks(m, par, uf, ui, hit, can_hit, f, g, alive, dist, tgt, fire, boom, dmg, heal)
            _move(m, par, uf, f, g, alive, way, dist, tgt, mode, fire, nx, ny)
            _separate(m, par, uf, collide, f, alive, nx, ny)


@njit(cache=True)
def _pairwise(f, m, dist):
    U = dist.shape[0]
    for i in range(U):
        for j in range(i + 1, U):
            dx = f[m, X, j] - f[m, X, i]
            dy = f[m, Y, j] - f[m, Y, i]
            d = math.sqrt(dx * dx + dy * dy)
            dist[i, j] = d
            dist[j, i] = d


@njit(cache=True)
def _hurt(f, uf, m, v):
    return f[m, HP, v] < uf[v, HP_MAX] - 1e-9


@njit(cache=True)
def _targets(m, N, par, uf, ui, can_hit, f, g, alive, dist, tgt, mode):
    """Each unit's target (-1: none) and movement mode for this sub-step."""
    U = alive.shape[1]
    for u in range(U):
        tgt[u] = -1
        mode[u] = M_HOLD
        if not alive[m, u]:
            continue
        if u < N:
            order = g[m, ORDER, u]
            if order == MOVE:
                mode[u] = M_DIR
            elif order == ATTACK:
                t = g[m, OTGT, u]
                ok = alive[m, t] and (
                    (ui[u, KIND] == HEALER and ui[t, HEALABLE] == 1) or can_hit[u, t]
                )
                if ok:
                    tgt[u] = t
                    mode[u] = M_CHASE
            elif ui[u, KIND] == HEALER:  # stopped medivac: heal auto-cast within range
                tgt[u] = _closest_friend(m, u, 0, N, uf, ui, f, alive, dist, True, uf[u, RANGE])
        elif ui[u, KIND] == HEALER:
            t = _closest_friend(m, u, N, U, uf, ui, f, alive, dist, True, 1e9)
            if t < 0:
                t = _closest_friend(m, u, N, U, uf, ui, f, alive, dist, False, 1e9)
            tgt[u] = t
            mode[u] = M_CHASE if t >= 0 else M_HOLD
        else:
            _attack_move(m, u, N, par, uf, ui, can_hit, g, alive, dist, tgt, mode)


@njit(cache=True)
def _closest_friend(m, u, lo, hi, uf, ui, f, alive, dist, hurt_only, reach):
    best, best_d = -1, 1e18
    for v in range(lo, hi):
        if v == u or not alive[m, v] or ui[v, HEALABLE] == 0:
            continue
        if hurt_only and not _hurt(f, uf, m, v):
            continue
        e = dist[u, v] - uf[u, RADIUS] - uf[v, RADIUS]
        if e <= reach and e < best_d:
            best, best_d = v, e
    return best


@njit(cache=True)
def _attack_move(m, u, N, par, uf, ui, can_hit, g, alive, dist, tgt, mode):
    """SC2 attack-move of an enemy: the closest hittable agent within acquire range (fighters
    first; a non-baneling prefers anything to a baneling), else on to the agents' spawn, else
    (arrived) the closest hittable agent. A non-baneling within a living agent baneling's
    burst radius (+ par[P_DODGE]) backs away from it unless it is that baneling's closest foe:
    one unit may take it on, the others keep out of the burst (splash avoidance)."""
    best, best_key, near, near_d = -1, 1e18, -1, 1e18
    dodge = ui[u, KIND] != BANE and par[P_DODGE] >= 0.0
    for a in range(N):
        if not alive[m, a] or not can_hit[u, a]:
            continue
        e = dist[u, a] - uf[u, RADIUS] - uf[a, RADIUS]
        bane = ui[a, KIND] == BANE
        close = dist[u, a] - uf[u, RADIUS] <= uf[a, SPLASH_R] + par[P_DODGE]
        if dodge and bane and close and not _closest_foe(m, a, u, N, uf, can_hit, alive, dist):
            tgt[u] = a
            mode[u] = M_FLEE
            return
        if e < near_d:
            near, near_d = a, e
        if e <= par[P_ACQUIRE]:
            key = e if ui[a, THREAT] == 1 else e + 1e6
            if dodge and bane:
                key += 1e3
            if key < best_key:
                best, best_key = a, key
    if best < 0 and g[m, ARRIVED, u] == 1:
        best = near
    tgt[u] = best
    if best >= 0:
        mode[u] = M_CHASE
    else:
        mode[u] = M_HOLD if g[m, ARRIVED, u] == 1 else M_WAY


@njit(cache=True)
def _closest_foe(m, a, u, N, uf, can_hit, alive, dist):
    """Whether enemy u is the closest (edge to edge) living enemy that can hit agent a."""
    d_u = dist[a, u] - uf[u, RADIUS]
    for v in range(N, alive.shape[1]):
        if v != u and alive[m, v] and can_hit[v, a] and dist[a, v] - uf[v, RADIUS] < d_u:
            return False
    return True


@njit(cache=True)
def _fire(m, par, uf, ui, f, alive, dist, tgt, mode, fire):
    """Who attacks (or heals) this sub-step; units with their target in range stop moving."""
    U = alive.shape[1]
    for u in range(U):
        fire[u] = False
        t = tgt[u]
        if t < 0 or mode[u] == M_FLEE:
            continue
        edge = dist[u, t] - uf[u, RADIUS] - uf[t, RADIUS]
        if edge > uf[u, RANGE]:
            continue
        if mode[u] == M_CHASE:
            mode[u] = M_HOLD
        if ui[u, KIND] == HEALER:
            fire[u] = f[m, EN, u] > 0.0 and _hurt(f, uf, m, t)
        else:
            fire[u] = f[m, CD, u] < par[P_LOOPS]


@njit(cache=True)
def _attacks(m, par, uf, ui, hit, can_hit, f, g, alive, dist, tgt, fire, boom, dmg, heal):
    """Resolve all attacks together, then deaths (killed banelings burst, which may chain),
    then cooldowns, energy and shield regeneration."""
    U = alive.shape[1]
    dmg[:, :] = 0.0
    heal[:] = 0.0
    for u in range(U):
        boom[u] = False
        g[m, LAST_TGT, u] = tgt[u] if fire[u] else -1
    for u in range(U):
        if not fire[u]:
            continue
        t, kind = tgt[u], ui[u, KIND]
        if kind == HEALER:
            room = max(uf[t, HP_MAX] - f[m, HP, t], 0.0)
            amt = min(uf[u, HEAL], f[m, EN, u] * uf[u, HP_PER_EN], room)
            heal[t] += amt
            f[m, EN, u] -= amt / uf[u, HP_PER_EN]
        elif kind == BANE:
            _burst(m, u, uf, hit, can_hit, alive, dist, dmg)
            boom[u] = True
            f[m, HP, u] = 0.0
        else:
            dmg[0, t] += hit[0, u, t]
            dmg[1, t] += hit[1, u, t]
            f[m, CD, u] += uf[u, CD_LOOPS]
            if kind == COLOSSUS:
                _lance(m, u, t, uf, hit, can_hit, f, alive, dmg)
    _tick(m, par, uf, f, alive, heal)
    _damage(m, f, alive, dmg)
    while _deaths(m, uf, ui, hit, can_hit, f, alive, dist, boom, dmg):
        _damage(m, f, alive, dmg)


@njit(cache=True)
def _burst(m, b, uf, hit, can_hit, alive, dist, dmg):
    """Baneling splash: every living hittable foe within the splash radius."""
    for v in range(alive.shape[1]):
        if alive[m, v] and can_hit[b, v] and dist[b, v] - uf[v, RADIUS] <= uf[b, SPLASH_R]:
            dmg[0, v] += hit[0, b, v]
            dmg[1, v] += hit[1, b, v]


@njit(cache=True)
def _lance(m, c, t, uf, hit, can_hit, f, alive, dmg):
    """Colossus line splash: foes near a segment through the target, across the line of fire."""
    fx = f[m, X, t] - f[m, X, c]
    fy = f[m, Y, t] - f[m, Y, c]
    norm = max(math.sqrt(fx * fx + fy * fy), 1e-9)
    ux, uy = fx / norm, fy / norm
    for v in range(alive.shape[1]):
        if v == t or not alive[m, v] or not can_hit[c, v]:
            continue
        ox = f[m, X, v] - f[m, X, t]
        oy = f[m, Y, v] - f[m, Y, t]
        along = abs(ox * ux + oy * uy)
        across = abs(-ox * uy + oy * ux)
        if along <= uf[c, SPLASH_W] + uf[v, RADIUS] and across <= uf[c, SPLASH_LEN]:
            dmg[0, v] += hit[0, c, v]
            dmg[1, v] += hit[1, c, v]


@njit(cache=True)
def _tick(m, par, uf, f, alive, heal):
    """Heals, cooldowns, energy; shields regenerate after a delay without damage."""
    loops = par[P_LOOPS]
    for v in range(alive.shape[1]):
        f[m, CD, v] = max(f[m, CD, v] - loops, 0.0)
        if not alive[m, v]:
            continue
        f[m, HP, v] = min(f[m, HP, v] + heal[v], uf[v, HP_MAX])
        f[m, EN, v] = min(f[m, EN, v] + uf[v, EN_REGEN], uf[v, EN_MAX])
        f[m, SINCE, v] += loops
        if f[m, SINCE, v] >= par[P_REGEN_DELAY]:
            f[m, SH, v] = min(f[m, SH, v] + par[P_REGEN], uf[v, SH_MAX])


@njit(cache=True)
def _damage(m, f, alive, dmg):
    """Shields take the raw damage first; the part that gets through hits armoured health.
    Damage queued for a unit that has died meanwhile is dropped."""
    for v in range(dmg.shape[1]):
        raw = dmg[1, v]
        health = dmg[0, v]
        dmg[0, v] = 0.0
        dmg[1, v] = 0.0
        if raw <= 0.0 or not alive[m, v]:
            continue
        absorbed = min(f[m, SH, v], raw)
        f[m, SH, v] -= absorbed
        f[m, HP, v] -= (raw - absorbed) / raw * health
        f[m, SINCE, v] = 0.0


@njit(cache=True)
def _deaths(m, uf, ui, hit, can_hit, f, alive, dist, boom, dmg):
    """Remove the dead; a baneling killed before bursting bursts now. True if one did."""
    burst = False
    for v in range(alive.shape[1]):
        if not alive[m, v] or f[m, HP, v] > 1e-9:
            continue
        alive[m, v] = False
        f[m, HP, v] = 0.0
        f[m, SH, v] = 0.0
        f[m, CD, v] = 0.0
        f[m, EN, v] = 0.0
        if ui[v, KIND] == BANE and not boom[v]:
            boom[v] = True
            _burst(m, v, uf, hit, can_hit, alive, dist, dmg)
            burst = True
    return burst


@njit(cache=True)
def _move(m, par, uf, f, g, alive, way, dist, tgt, mode, fire, nx, ny):
    """Chasers close in to their range, move orders go the unit's speed, enemies with
    nobody in reach walk to the agents' spawn; units that attacked stand still."""
    U = alive.shape[1]
    for u in range(U):
        x, y = f[m, X, u], f[m, Y, u]
        nx[u], ny[u] = x, y
        if not alive[m, u] or fire[u]:
            continue
        step = uf[u, STEP]
        if mode[u] == M_CHASE:
            t = tgt[u]
            d = max(dist[u, t], 1e-9)
            gap = dist[u, t] - uf[u, RADIUS] - uf[t, RADIUS] - uf[u, RANGE] + 0.05
            s = min(step, max(gap, 0.0))
            nx[u] = x + (f[m, X, t] - x) / d * s
            ny[u] = y + (f[m, Y, t] - y) / d * s
        elif mode[u] == M_FLEE:
            t = tgt[u]
            d = max(dist[u, t], 1e-9)
            nx[u] = x - (f[m, X, t] - x) / d * step
            ny[u] = y - (f[m, Y, t] - y) / d * step
        elif mode[u] == M_DIR:
            k = g[m, MDIR, u]
            s = min(step, f[m, REM, u])
            nx[u] = x + _DX[k] * s
            ny[u] = y + _DY[k] * s
            f[m, REM, u] -= s
        elif mode[u] == M_WAY:
            wx, wy = way[m, 0] + uf[u, WAY_DX] - x, way[m, 1] + uf[u, WAY_DY] - y
            d = max(math.sqrt(wx * wx + wy * wy), 1e-9)
            s = min(step, d)
            nx[u] = x + wx / d * s
            ny[u] = y + wy / d * s
            if d - s <= par[P_ARRIVE]:
                g[m, ARRIVED, u] = 1


@njit(cache=True)
def _separate(m, par, uf, collide, f, alive, nx, ny):
    """Overlapping living ground units push each other apart (relaxation passes)."""
    U = alive.shape[1]
    w, h = par[P_MAP_W] - 1e-3, par[P_MAP_H] - 1e-3
    for i in range(U):
        f[m, X, i] = nx[i]
        f[m, Y, i] = ny[i]
    for _ in range(SEPARATION_PASSES):
        for i in range(U):
            if not alive[m, i]:
                continue
            for j in range(i + 1, U):
                if not alive[m, j] or not collide[i, j]:
                    continue
                dx, dy = f[m, X, j] - f[m, X, i], f[m, Y, j] - f[m, Y, i]
                d = math.sqrt(dx * dx + dy * dy)
                overlap = uf[i, RADIUS] + uf[j, RADIUS] - d
                if overlap <= 0.0:
                    continue
                if d < 1e-6:
                    dx, d = 1.0, 1.0
                push = 0.5 * overlap / d
                f[m, X, i] -= push * dx
                f[m, Y, i] -= push * dy
                f[m, X, j] += push * dx
                f[m, Y, j] += push * dy
    for i in range(U):
        f[m, X, i] = min(max(f[m, X, i], 0.0), w)
        f[m, Y, i] = min(max(f[m, Y, i], 0.0), h)

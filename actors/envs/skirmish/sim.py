"""Batched combat dynamics: M independent battles stepped together with NumPy.

Unit u of every battle is agent u for u < N and enemy u - N after that. All per-unit state is
an [M, U] array; interactions use [M, U, U] pairwise matrices (`dx[m, i, j] = x_j - x_i`).
Each agent step runs `substeps` physics sub-steps of `step_mul / substeps` game loops:

1. targets: agents follow their orders (attack/heal a unit, move, stop); idle agents fire at
   the closest enemy in range; enemies follow SC2's attack-move AI (chase and attack the
   closest living agent); healers heal the closest damaged friend.
2. attacks resolve simultaneously: single-target hits, the baneling's suicide splash, the
   colossus' line splash, medivac heals (energy), shields before armoured health.
3. units that are not firing move (chase or move order), then overlapping ground units push
   apart (separation), so crowds block paths.
"""

from __future__ import annotations

import numpy as np

from actors.envs.skirmish.spec import (
    KINDS,
    LOOPS_PER_SECOND,
    MapSpec,
    SkirmishConfig,
    ordered_units,
    unit_types,
)

IDLE, MOVE, ATTACK = 0, 1, 2
INF = np.float64(1e9)


class Statics:
    """Per-unit constants of a map (shapes [U] or [U, U]); identical in all M battles."""

    def __init__(self, spec: MapSpec, cfg: SkirmishConfig):
        types = unit_types()
        a_names, a_pos = ordered_units(spec, "allies")
        e_names, e_pos = ordered_units(spec, "enemies")
        self.names = a_names + e_names
        self.N, self.E = len(a_names), len(e_names)
        self.U = self.N + self.E
        ut = [types[n] for n in self.names]
        self.types = ut
        loop = cfg.step_mul // cfg.substeps
        self.loops = float(loop)
        self.team = np.array([0] * self.N + [1] * self.E)
        self.hp_max = np.array([t.hp for t in ut])
        self.sh_max = np.array([t.shield for t in ut])
        self.range = np.array([t.range for t in ut])
        self.radius = np.array([t.radius for t in ut])
        self.step_len = np.array([t.speed for t in ut]) / LOOPS_PER_SECOND * loop
        self.cd_loops = np.array([t.cooldown_s for t in ut]) * LOOPS_PER_SECOND
        self.kind = np.array([KINDS.index(t.kind) for t in ut])
        self.air = np.array(["air" in t.attributes for t in ut])
        self.massive = np.array(["massive" in t.attributes for t in ut])
        self.energy_max = np.array([t.energy_max for t in ut])
        self.energy_start = np.array([t.energy_start for t in ut])
        self.energy_regen = np.array([t.energy_regen_s for t in ut]) / LOOPS_PER_SECOND * loop
        self.smac_cd = np.array([t.smac_max_cooldown for t in ut])
        self.start_pos = np.concatenate([a_pos, e_pos])
        hits = np.array([[a.hit_vs(v) for v in ut] for a in ut]).reshape(self.U, self.U, 2)
        self.foe = self.team[:, None] != self.team[None, :]
        self.hit_h = np.where(self.foe, hits[..., 0], 0.0)
        self.hit_s = np.where(self.foe, hits[..., 1], 0.0)
        ground = ~self.air
        # Colossi step over small units; everything else on the ground collides.
        self.collide = (
            ground[:, None] & ground[None, :] & (self.massive[:, None] == self.massive[None, :])
        )
        np.fill_diagonal(self.collide, False)
        self.healers = np.flatnonzero(self.kind == KINDS.index("healer"))
        self.banes = np.flatnonzero(self.kind == KINDS.index("baneling"))
        self.colossi = np.flatnonzero(self.kind == KINDS.index("colossus"))
        self.shooter = np.isin(self.kind, [KINDS.index(k) for k in ("ranged", "melee", "colossus")])
        self.heal_amount = np.array([t.heal_per_s for t in ut]) / LOOPS_PER_SECOND * loop
        self.hp_per_energy = np.array([t.hp_per_energy for t in ut])
        self.splash_radius = np.array([t.splash_radius for t in ut])
        self.splash_len = np.array([t.splash_half_length for t in ut])
        self.splash_width = np.array([t.splash_half_width for t in ut])
        self.healable = ~self.air & (self.kind != KINDS.index("healer"))
        self.map_w, self.map_h = spec.map_size


class Battle:
    """Dynamic state of M battles of one map.

    Shapes: x, y, hp, sh, cd, energy, since_dmg, alive, order, order_tgt: [M, U];
    move_dir: [M, U, 2].
    """

    def __init__(self, st: Statics, cfg: SkirmishConfig, num_envs: int):
        self.st, self.cfg, self.M = st, cfg, num_envs
        M, U = num_envs, st.U
        self.x = np.zeros((M, U))
        self.y = np.zeros((M, U))
        self.hp = np.zeros((M, U))
        self.sh = np.zeros((M, U))
        self.cd = np.zeros((M, U))
        self.energy = np.zeros((M, U))
        self.since_dmg = np.zeros((M, U))
        self.alive = np.zeros((M, U), bool)
        self.order = np.zeros((M, U), np.int64)
        self.order_tgt = np.full((M, U), -1, np.int64)
        self.move_dir = np.zeros((M, U, 2))
        self.last_fire = np.zeros((M, U), bool)  # for rendering: who attacked whom last
        self.last_tgt = np.full((M, U), -1, np.int64)
        self._m = np.arange(M)[:, None]
        self._u = np.arange(U)[None, :]
        self._is_healer = np.isin(np.arange(U), st.healers)
        self._regen_delay = cfg.shield_regen_delay_s * LOOPS_PER_SECOND
        self._regen = cfg.shield_regen_per_s / LOOPS_PER_SECOND * st.loops

    def reset(self, envs: np.ndarray, rngs: list[np.random.Generator]) -> None:
        """Put battles `envs` (indices) at their start, each jittered by its own generator."""
        st, j, uj = self.st, self.cfg.start_jitter, self.cfg.unit_jitter
        for m in envs:
            # Each side's formation shifts as a whole; units move a little within it.
            shift = rngs[m].uniform(-j, j, size=(2, 2))[st.team]
            noise = shift + rngs[m].uniform(-uj, uj, size=(st.U, 2))
            self.x[m] = np.clip(st.start_pos[:, 0] + noise[:, 0], 0, st.map_w - 1e-3)
            self.y[m] = np.clip(st.start_pos[:, 1] + noise[:, 1], 0, st.map_h - 1e-3)
        self.hp[envs] = st.hp_max
        self.sh[envs] = st.sh_max
        self.cd[envs] = 0.0
        self.energy[envs] = st.energy_start
        self.since_dmg[envs] = 0.0
        self.alive[envs] = True
        self.order[envs] = IDLE
        self.order_tgt[envs] = -1
        self.move_dir[envs] = 0.0
        self.last_fire[envs] = False
        self.last_tgt[envs] = -1

    # -- geometry ---------------------------------------------------------------------------
    def pairwise(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """dx, dy, dist [M, U, U] with dx[m, i, j] = x_j - x_i."""
        dx = self.x[:, None, :] - self.x[:, :, None]
        dy = self.y[:, None, :] - self.y[:, :, None]
        return dx, dy, np.sqrt(dx * dx + dy * dy)

    # -- one physics sub-step ---------------------------------------------------------------
    def substep(self, active: np.ndarray) -> None:
        """Advance the `active` battles by one sub-step (inactive ones are left untouched)."""
        st = self.st
        dx, dy, dist = self.pairwise()
        edge = dist - st.radius[None, :, None] - st.radius[None, None, :]
        tgt, chase_ok = self._targets(dist, edge)
        has = tgt >= 0
        tc = np.maximum(tgt, 0)
        d_t = edge[self._m, self._u, tc]
        in_rng = has & (d_t <= st.range)
        alive = self.alive & active[:, None]
        heal_ok = self.energy > 0
        fire = alive & in_rng & np.where(self._is_healer, heal_ok, self.cd < st.loops)
        self._resolve_attacks(fire, tc, dist, dx, dy)
        chase = alive & has & ~in_rng & chase_ok
        self._move(chase, tc, dx, dy, dist, d_t, alive & ~fire & ~chase & (self.order == MOVE))
        self._separate(active)
        self.cd = np.where(active[:, None], np.maximum(self.cd - st.loops, 0.0), self.cd)
        self.energy = np.minimum(self.energy + st.energy_regen * alive, st.energy_max)
        self.last_fire = np.where(active[:, None], fire, self.last_fire)
        self.last_tgt = np.where(active[:, None], np.where(fire, tgt, -1), self.last_tgt)

    def _targets(self, dist: np.ndarray, edge: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each unit's target [M, U] (-1: none) and whether it may chase it [M, U]."""
        st, N = self.st, self.st.N
        foe_alive = st.foe[None] & self.alive[:, None, :]
        e = np.where(foe_alive, edge, INF)
        closest = e.argmin(axis=2)
        closest_d = e[self._m, self._u, closest]
        exists = closest_d < INF
        # Scripted enemies (attack-move) chase and attack the closest living agent.
        tgt = np.where(exists, closest, -1)
        # Agents: idle ones fire at the closest enemy in range without chasing.
        auto = exists[:, :N] & (closest_d[:, :N] <= st.range[:N])
        agent_tgt = np.where(auto, closest[:, :N], -1)
        ordered = self.order[:, :N] == ATTACK
        ot = np.maximum(self.order_tgt[:, :N], 0)
        ot_alive = self.alive[self._m, ot]
        agent_tgt = np.where(ordered & ot_alive, self.order_tgt[:, :N], agent_tgt)
        agent_tgt = np.where(self.order[:, :N] == MOVE, -1, agent_tgt)
        tgt[:, :N] = agent_tgt
        chase = np.ones_like(tgt, bool)
        chase[:, :N] = ordered & ot_alive
        if st.healers.size:
            self._healer_targets(tgt, chase, dist)
        return tgt, chase

    def _healer_targets(self, tgt: np.ndarray, chase: np.ndarray, dist: np.ndarray) -> None:
        """Healers: ordered agents keep their heal target; others pick the closest damaged
        friend (enemy healers follow the closest friend when nobody is hurt)."""
        st, h = self.st, self.st.healers
        friend = (st.team[h][:, None] == st.team[None, :]) & st.healable[None, :]
        ok = friend[None] & self.alive[:, None, :]
        hurt = self.hp < st.hp_max - 1e-9
        d = np.where(ok, dist[:, h, :] + np.where(hurt[:, None, :], 0.0, 1e6), INF)
        best = d.argmin(axis=2)
        best_d = d[self._m, np.arange(len(h))[None], best]
        is_agent = h < st.N
        auto = np.where(is_agent[None], best_d <= st.range[h], best_d < INF)
        pick = np.where(auto, best, -1)
        ordered = (self.order[:, h] == ATTACK) & is_agent[None]
        ot = np.maximum(self.order_tgt[:, h], 0)
        ot_ok = ordered & self.alive[self._m, ot]
        pick = np.where(ot_ok, self.order_tgt[:, h], pick)
        tgt[:, h] = np.where(self.order[:, h] == MOVE, -1, pick)
        chase[:, h] = ot_ok | ~is_agent[None]

    def _resolve_attacks(self, fire, tc, dist, dx, dy) -> None:
        st, M, U = self.st, self.M, self.st.U
        shoot = fire & st.shooter[None]
        flat = (self._m * U + tc).ravel()
        dmg_h = np.bincount(flat, (shoot * st.hit_h[self._u, tc]).ravel(), M * U).reshape(M, U)
        dmg_s = np.bincount(flat, (shoot * st.hit_s[self._u, tc]).ravel(), M * U).reshape(M, U)
        if st.banes.size:
            b = st.banes
            boom = fire[:, b]
            reach = dist[:, b, :] - st.radius[None, None, :] <= st.splash_radius[b][None, :, None]
            hit = boom[..., None] & reach & self.alive[:, None, :]
            dmg_h += (hit * st.hit_h[b][None]).sum(1)
            dmg_s += (hit * st.hit_s[b][None]).sum(1)
            self.hp[:, b] = np.where(boom, 0.0, self.hp[:, b])
        if st.colossi.size:
            hit = self._line_splash(fire, tc, dx, dy)
            c = st.colossi
            dmg_h += (hit * st.hit_h[c][None]).sum(1)
            dmg_s += (hit * st.hit_s[c][None]).sum(1)
        heal = np.zeros((M, U))
        if st.healers.size:
            h = st.healers
            ht = tc[:, h]
            room = st.hp_max[ht] - self.hp[self._m, ht]
            amt = np.minimum(st.heal_amount[h], self.energy[:, h] * st.hp_per_energy[h])
            amt = np.where(fire[:, h], np.minimum(amt, np.maximum(room, 0.0)), 0.0)
            self.energy[:, h] -= amt / st.hp_per_energy[h]
            np.add.at(heal, (np.arange(M)[:, None], ht), amt)
        self._apply(dmg_h, dmg_s, heal)
        self.cd = np.where(fire & st.shooter[None], self.cd + st.cd_loops, self.cd)

    def _line_splash(self, fire, tc, dx, dy) -> np.ndarray:
        """Victims [M, C, U] of each firing colossus' lances besides its main target:
        units near a segment through the target, perpendicular to the line of fire."""
        st, c = self.st, self.st.colossi
        M = self.M
        t = tc[:, c]  # [M, C]
        m_idx = np.arange(M)[:, None]
        fx, fy = dx[m_idx, c[None], t], dy[m_idx, c[None], t]
        norm = np.maximum(np.hypot(fx, fy), 1e-9)
        ux, uy = fx / norm, fy / norm
        # Offsets of every unit from the target: dx[m, t, v].
        ox, oy = dx[m_idx, t, :], dy[m_idx, t, :]
        along = np.abs(ox * ux[..., None] + oy * uy[..., None])
        across = np.abs(-ox * uy[..., None] + oy * ux[..., None])
        near = (along <= st.splash_width[c][None, :, None] + st.radius[None, None, :]) & (
            across <= st.splash_len[c][None, :, None]
        )
        foe = st.foe[c][None] & self.alive[:, None, :]
        not_main = np.arange(st.U)[None, None, :] != t[..., None]
        return fire[:, c][..., None] & near & foe & not_main

    def _apply(self, dmg_h: np.ndarray, dmg_s: np.ndarray, heal: np.ndarray) -> None:
        """Shields take damage first; what gets through hits armoured health."""
        st = self.st
        absorbed = np.minimum(self.sh, dmg_s)
        through = np.where(dmg_s > 0, (dmg_s - absorbed) / np.maximum(dmg_s, 1e-12), 0.0)
        self.sh -= absorbed
        self.hp = np.minimum(self.hp - through * dmg_h + heal, st.hp_max)
        hurt = dmg_s > 0
        self.since_dmg = np.where(hurt, 0.0, self.since_dmg + st.loops)
        regen = (self.since_dmg >= self._regen_delay) & self.alive
        self.sh = np.where(regen, np.minimum(self.sh + self._regen, st.sh_max), self.sh)
        dead = self.alive & (self.hp <= 1e-9)
        self.alive &= ~dead
        self.hp = np.where(self.alive, self.hp, 0.0)
        self.sh = np.where(self.alive, self.sh, 0.0)
        self.cd = np.where(self.alive, self.cd, 0.0)
        self.energy = np.where(self.alive, self.energy, 0.0)

    def _move(self, chase, tc, dx, dy, dist, d_t, movers) -> None:
        st = self.st
        m, u = self._m, self._u
        tx, ty = dx[m, u, tc], dy[m, u, tc]
        td = np.maximum(dist[m, u, tc], 1e-9)
        step = np.minimum(st.step_len, np.maximum(d_t - st.range + 0.05, 0.0))
        vx = np.where(chase, tx / td * step, 0.0)
        vy = np.where(chase, ty / td * step, 0.0)
        vx = np.where(movers, self.move_dir[..., 0] * st.step_len, vx)
        vy = np.where(movers, self.move_dir[..., 1] * st.step_len, vy)
        self.x += vx
        self.y += vy

    def _separate(self, active: np.ndarray) -> None:
        """Push overlapping living ground units apart (half the overlap each)."""
        st = self.st
        dx, dy, dist = self.pairwise()
        both = self.alive[:, :, None] & self.alive[:, None, :] & st.collide[None]
        overlap = st.radius[:, None] + st.radius[None, :] - dist
        push = np.where(both & (overlap > 0), 0.5 * overlap / np.maximum(dist, 1e-6), 0.0)
        push *= active[:, None, None]
        self.x = np.clip(self.x - (push * dx).sum(2), 0.0, st.map_w - 1e-3)
        self.y = np.clip(self.y - (push * dy).sum(2), 0.0, st.map_h - 1e-3)

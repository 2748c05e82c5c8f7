"""Battle state of M independent battles of one map, stepped by the numba kernels.

Unit u of every battle is agent u for u < N and enemy u - N after that. `Statics` holds the
per-unit constants (identical in all M battles) both as named NumPy arrays (read by the views,
scripts and renderer) and packed for the kernels; `Battle` holds the dynamic state packed in
two arrays with named [M, U] views. Each agent step runs `substeps` physics sub-steps of
`step_mul / substeps` game loops; see `kernels.py` for what happens in one.
"""

from __future__ import annotations

import numpy as np

from actors.envs.skirmish import kernels as K
from actors.envs.skirmish.spec import (
    KINDS,
    LOOPS_PER_SECOND,
    MapSpec,
    SkirmishConfig,
    ordered_units,
    unit_types,
)

IDLE, MOVE, ATTACK = K.IDLE, K.MOVE, K.ATTACK
ARRIVE_RADIUS = 3.0  # an enemy this close to the agents' spawn has arrived and starts hunting


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
        self.team = np.array([0] * self.N + [1] * self.E, np.int64)
        self.hp_max = np.array([t.hp for t in ut], np.float64)
        self.sh_max = np.array([t.shield for t in ut], np.float64)
        self.range = np.array([t.range for t in ut], np.float64)
        self.radius = np.array([t.radius for t in ut], np.float64)
        self.kind = np.array([KINDS.index(t.kind) for t in ut])
        self.air = np.array(["air" in t.attributes for t in ut])
        self.energy_start = np.array([t.energy_start for t in ut], np.float64)
        self.smac_cd = np.array([t.smac_max_cooldown for t in ut], np.float64)
        self.start_pos = np.concatenate([a_pos, e_pos])
        self.healers = np.flatnonzero(self.kind == KINDS.index("healer"))
        self.healable = ~self.air & (self.kind != KINDS.index("healer"))
        self.map_w, self.map_h = spec.map_size
        point = spec.attack_point
        goal = np.array(point) if point is not None else self.start_pos[: self.N].mean(0)
        self.goal = np.asarray(goal, np.float64)
        self._pack(ut, cfg, loop)

    def _pack(self, ut: list, cfg: SkirmishConfig, loop: int) -> None:
        """The kernels' arrays: uf, ui, hit, can_hit, collide, par (see kernels.py)."""
        per_loop = loop / LOOPS_PER_SECOND
        uf = np.zeros((self.U, K.N_UF))
        uf[:, K.HP_MAX], uf[:, K.SH_MAX] = self.hp_max, self.sh_max
        uf[:, K.RANGE], uf[:, K.RADIUS] = self.range, self.radius
        uf[:, K.STEP] = [t.speed * per_loop for t in ut]
        uf[:, K.CD_LOOPS] = [t.cooldown_s * LOOPS_PER_SECOND for t in ut]
        uf[:, K.EN_MAX] = [t.energy_max for t in ut]
        uf[:, K.EN_REGEN] = [t.energy_regen_s * per_loop for t in ut]
        uf[:, K.HEAL] = [t.heal_per_s * per_loop for t in ut]
        uf[:, K.HP_PER_EN] = [t.hp_per_energy for t in ut]
        uf[:, K.SPLASH_R] = [t.splash_radius for t in ut]
        uf[:, K.SPLASH_LEN] = [t.splash_half_length for t in ut]
        uf[:, K.SPLASH_W] = [t.splash_half_width for t in ut]
        enemy_pos = self.start_pos[self.N :]
        uf[self.N :, K.WAY_DX : K.WAY_DY + 1] = enemy_pos - enemy_pos.mean(0)
        ui = np.zeros((self.U, K.N_UI), np.int64)
        ui[:, K.TEAM], ui[:, K.KIND], ui[:, K.HEALABLE] = self.team, self.kind, self.healable
        ui[:, K.THREAT] = [t.hits > 0 for t in ut]
        foe = self.team[:, None] != self.team[None, :]
        reach = np.array([[t.hits > 0 and (t.hits_air or not v) for v in self.air] for t in ut])
        self.can_hit = foe & reach.reshape(self.U, self.U)
        hits = np.array([[a.hit_vs(v) for v in ut] for a in ut]).reshape(self.U, self.U, 2)
        self.hit = np.ascontiguousarray(np.where(self.can_hit[None], hits.transpose(2, 0, 1), 0.0))
        ground = ~self.air
        massive = np.array(["massive" in t.attributes for t in ut])
        # Colossi step over small units; everything else on the ground collides.
        self.collide = ground[:, None] & ground[None, :] & (massive[:, None] == massive[None, :])
        np.fill_diagonal(self.collide, False)
        par = np.zeros(K.N_PAR)
        par[K.P_LOOPS], par[K.P_MAP_W], par[K.P_MAP_H] = loop, self.map_w, self.map_h
        par[K.P_REGEN_DELAY] = cfg.shield_regen_delay_s * LOOPS_PER_SECOND
        par[K.P_REGEN] = cfg.shield_regen_per_s * per_loop
        par[K.P_ACQUIRE], par[K.P_ARRIVE] = cfg.acquire_range, ARRIVE_RADIUS
        par[K.P_DODGE] = cfg.bane_dodge
        self.uf, self.ui, self.par = uf, ui, par


class Battle:
    """Dynamic state of M battles of one map.

    Storage: f [M, N_F, U] float64 and g [M, N_G, U] int64 (kernels.py), alive [M, U] bool,
    way [M, 2] the agents' spawn (the enemy's attack-move goal). Named views, all [M, U]:
    x, y, hp, sh, cd, energy, since_dmg, order, order_tgt (target unit index, -1 none),
    last_tgt (whom each unit attacked or healed in the last sub-step, -1 none), last_fire.
    """

    def __init__(self, st: Statics, cfg: SkirmishConfig, num_envs: int):
        self.st, self.cfg, self.M = st, cfg, num_envs
        self.f = np.zeros((num_envs, K.N_F, st.U))
        self.g = np.zeros((num_envs, K.N_G, st.U), np.int64)
        self.alive = np.zeros((num_envs, st.U), bool)
        self.way = np.zeros((num_envs, 2))
        self._before = np.zeros((num_envs, 4))

    x = property(lambda self: self.f[:, K.X])
    y = property(lambda self: self.f[:, K.Y])
    hp = property(lambda self: self.f[:, K.HP])
    sh = property(lambda self: self.f[:, K.SH])
    cd = property(lambda self: self.f[:, K.CD])
    energy = property(lambda self: self.f[:, K.EN])
    since_dmg = property(lambda self: self.f[:, K.SINCE])
    order = property(lambda self: self.g[:, K.ORDER])
    order_tgt = property(lambda self: self.g[:, K.OTGT])
    last_tgt = property(lambda self: self.g[:, K.LAST_TGT])
    last_fire = property(lambda self: self.g[:, K.LAST_TGT] >= 0)

    def reset(self, envs: np.ndarray, rngs: list[np.random.Generator]) -> None:
        """Put battles `envs` (indices) at their start, each jittered by its own generator:
        each side's formation shifts as a whole; units move a little within it."""
        st, cfg = self.st, self.cfg
        envs = np.asarray(envs, np.int64).reshape(-1)
        draws = np.empty((envs.size, 4 + 2 * st.U))
        for r, m in enumerate(envs.tolist()):
            draws[r] = rngs[m].random(4 + 2 * st.U)
        jitter = np.array([cfg.start_jitter, cfg.unit_jitter, st.map_w - 1e-3, st.map_h - 1e-3])
        K.reset_battles(envs, draws, jitter, st.start_pos, st.goal, st.team, st.uf,
                        st.energy_start, self.f, self.g, self.alive, self.way)  # fmt: skip

    def step(self, active: np.ndarray) -> np.ndarray:
        """Advance the `active` [M] battles by one agent step (all sub-steps).

        Returns [M, 4]: each battle's (enemy health + shields, ally health + shields, dead
        enemies, dead allies) before the step (rows of inactive battles are stale).
        """
        st = self.st
        K.advance(
            active, self.cfg.substeps, st.N, st.par, st.uf, st.ui, st.hit, st.can_hit,
            st.collide, self.f, self.g, self.alive, self.way, self._before,
        )  # fmt: skip
        return self._before

    def pairwise(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """dx, dy, dist [M, U, U] with dx[m, i, j] = x_j - x_i (for scripts and tests)."""
        x, y = np.ascontiguousarray(self.x), np.ascontiguousarray(self.y)
        dx = x[:, None, :] - x[:, :, None]
        dy = y[:, None, :] - y[:, :, None]
        return dx, dy, np.sqrt(dx * dx + dy * dy)

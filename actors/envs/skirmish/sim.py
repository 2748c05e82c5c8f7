"""Battle state of M independent battles of one map, stepped by the numba kernels.

Unit u of every battle is agent u for u < N and enemy u - N after that. Which unit type
each u is, and where it starts, is the battle's *roster*. A fixed map has one roster shared
by its M battles; a randomised map (SMACv2-style, `scenario.py`) draws a roster per battle
at every reset. `Statics` holds what every battle of the map shares (sizes, kernel scalars,
the `TypeTable` of the map's unit types and, for a fixed map, its roster as named NumPy
arrays); `Rosters` holds R rosters' per-unit constants as kernel arrays (R = 1 fixed, M
randomised; battle m uses row `Battle.rid[m]`); `Battle` holds the dynamic state packed in
two arrays with named [M, U] views. Each agent step runs `substeps` physics sub-steps of
`step_mul / substeps` game loops; see `kernels.py` for what happens in one.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from actors.envs.skirmish import kernels as K
from actors.envs.skirmish import step_kernels
from actors.envs.skirmish.config import SkirmishConfig
from actors.envs.skirmish.scenario import draw_points, draw_teams, place
from actors.envs.skirmish.spec import KINDS, LOOPS_PER_SECOND, MapSpec, ordered_units, unit_types

IDLE, MOVE, ATTACK = K.IDLE, K.MOVE, K.ATTACK
ARRIVE_RADIUS = 3.0  # an enemy this close to the agents' spawn has arrived and starts hunting
HEALER = KINDS.index("healer")


class TypeTable:
    """Per-type constants of a map's unit types (row t is `names[t]`).

    Kernel rows uf [T, N_UF] (WAY columns zero), kind, air, threat, healable, massive [T],
    hit [2, T, T] (one attack of type a on type v: to health after armour, to shields),
    reach [T, T] (a's weapon reaches v: ground / air); hp, sh, smac_cd, energy_start,
    radius [T]; sight and shoot [T] (SMAC's fixed 9 / 6, or the unit's own with the map's
    `unit_ranges`); onehot [2, T, bits] (allies' and enemies' type one-hot order).
    """

    def __init__(self, spec: MapSpec, cfg: SkirmishConfig, loop: int):
        names = spec.pool
        ut = [unit_types()[n] for n in names]
        self.names, self.index = names, {n: t for t, n in enumerate(names)}
        per_loop = loop / LOOPS_PER_SECOND
        uf = np.zeros((len(ut), K.N_UF))
        uf[:, K.HP_MAX] = [t.hp for t in ut]
        uf[:, K.SH_MAX] = [t.shield for t in ut]
        uf[:, K.RANGE] = [t.range for t in ut]
        uf[:, K.RADIUS] = [t.radius for t in ut]
        uf[:, K.STEP] = [t.speed * per_loop for t in ut]
        uf[:, K.CD_LOOPS] = [t.cooldown_s * LOOPS_PER_SECOND for t in ut]
        uf[:, K.EN_MAX] = [t.energy_max for t in ut]
        uf[:, K.EN_REGEN] = [t.energy_regen_s * per_loop for t in ut]
        uf[:, K.HEAL] = [t.heal_per_s * per_loop for t in ut]
        uf[:, K.HP_PER_EN] = [t.hp_per_energy for t in ut]
        uf[:, K.SPLASH_R] = [t.splash_radius for t in ut]
        uf[:, K.SPLASH_LEN] = [t.splash_half_length for t in ut]
        uf[:, K.SPLASH_W] = [t.splash_half_width for t in ut]
        self.uf = uf
        self.hp, self.sh, self.radius = uf[:, K.HP_MAX], uf[:, K.SH_MAX], uf[:, K.RADIUS]
        self.kind = np.array([KINDS.index(t.kind) for t in ut], np.int64)
        self.air = np.array(["air" in t.attributes for t in ut])
        self.massive = np.array(["massive" in t.attributes for t in ut])
        self.threat = np.array([t.hits > 0 for t in ut])
        self.healable = ~self.air & (self.kind != HEALER)
        self.energy_start = np.array([t.energy_start for t in ut], np.float64)
        self.smac_cd = np.array([t.smac_max_cooldown for t in ut], np.float64)
        self.reach = np.array(
            [[a.hits > 0 and (a.hits_air or not v) for v in self.air] for a in ut]
        )
        hits = np.array([[a.hit_vs(v) for v in ut] for a in ut]).reshape(len(ut), len(ut), 2)
        self.hit = np.ascontiguousarray(hits.transpose(2, 0, 1))
        if spec.unit_ranges:
            self.sight = np.array([t.sight for t in ut], np.float64)
            self.shoot = np.array([max(t.range, spec.min_attack_range) for t in ut], np.float64)
        else:
            self.sight = np.full(len(ut), cfg.sight_range)
            self.shoot = np.full(len(ut), cfg.shoot_range)
        self.onehot = np.zeros((2, len(ut), spec.unit_type_bits))
        if spec.unit_type_bits:
            for side, order in enumerate((spec.ally_types, spec.enemy_types)):
                for t, n in enumerate(names):
                    if n in order:
                        self.onehot[side, t, order.index(n)] = 1.0


class Rosters:
    """R rosters of a map: per-unit constants gathered from its `TypeTable` by `set`.

    Kernel arrays: uf [R, U, N_UF], ui [R, U, N_UI], hit [R, 2, U, U], can_hit and
    collide [R, U, U], energy_start [R, U], start_pos [R, U, 2], goal [R, 2] (where the
    enemy attack-moves). Views: onehot [R, U, bits], inv_hp and sh_norm [R, U], healable
    [R, U], and per agent cool_norm (1 / SMAC's max cooldown; negative: a healer, whose
    energy stands in), agent_healer, sight, shoot [R, N]. Also tidx [R, U] (type row of each
    unit) and enemy_total [R] (the enemy's health + shields, for the reward scale).
    """

    def __init__(self, st: Statics, R: int):
        U, N = st.U, st.N
        self.st, self.N = st, N
        self.team = st.team
        self.tidx = np.zeros((R, U), np.int64)
        self.uf = np.zeros((R, U, K.N_UF))
        self.ui = np.zeros((R, U, K.N_UI), np.int64)
        self.hit = np.zeros((R, 2, U, U))
        self.can_hit = np.zeros((R, U, U), bool)
        self.collide = np.zeros((R, U, U), bool)
        self.energy_start = np.zeros((R, U))
        self.start_pos = np.zeros((R, U, 2))
        self.goal = np.zeros((R, 2))
        self.onehot = np.zeros((R, U, st.table.onehot.shape[2]))
        self.inv_hp, self.sh_norm = np.zeros((R, U)), np.zeros((R, U))
        self.healable = np.zeros((R, U), bool)
        self.cool_norm, self.sight, self.shoot = (np.zeros((R, N)) for _ in range(3))
        self.agent_healer = np.zeros((R, N), bool)
        self.enemy_total = np.zeros(R)

    def set(self, r: int, tidx: np.ndarray, pos: np.ndarray, way_off: np.ndarray, goal) -> None:
        """Row r: unit types `tidx` [U] (TypeTable rows), start positions [U, 2], each enemy's
        offset from its group's centre [U, 2] (kept on the attack-move) and the goal [2]."""
        tt, N, team = self.st.table, self.N, self.team
        self.tidx[r] = tidx
        uf = tt.uf[tidx]
        uf[N:, K.WAY_DX : K.WAY_DY + 1] = way_off[N:]
        self.uf[r] = uf
        kind = tt.kind[tidx]
        self.ui[r, :, K.TEAM], self.ui[r, :, K.KIND] = team, kind
        self.ui[r, :, K.HEALABLE], self.ui[r, :, K.THREAT] = tt.healable[tidx], tt.threat[tidx]
        foe = team[:, None] != team[None, :]
        self.can_hit[r] = foe & tt.reach[tidx][:, tidx]
        self.hit[r] = np.where(self.can_hit[r][None], tt.hit[:, tidx][:, :, tidx], 0.0)
        ground, massive = ~tt.air[tidx], tt.massive[tidx]
        # Colossi step over small units; everything else on the ground collides.
        col = ground[:, None] & ground[None, :] & (massive[:, None] == massive[None, :])
        np.fill_diagonal(col, False)
        self.collide[r] = col
        self.energy_start[r] = tt.energy_start[tidx]
        self.start_pos[r], self.goal[r] = pos, goal
        self.onehot[r, :N], self.onehot[r, N:] = tt.onehot[0, tidx[:N]], tt.onehot[1, tidx[N:]]
        sh = tt.sh[tidx]
        self.inv_hp[r] = 1.0 / tt.hp[tidx]
        self.sh_norm[r] = np.where(sh > 0, 1.0 / np.maximum(sh, 1e-9), 0.0)
        self.healable[r] = tt.healable[tidx]
        healer = kind[:N] == HEALER
        cd_norm = 1.0 / tt.smac_cd[tidx[:N]]
        self.cool_norm[r] = np.where(healer, -cd_norm, cd_norm)
        self.agent_healer[r] = healer
        self.sight[r], self.shoot[r] = tt.sight[tidx[:N]], tt.shoot[tidx[:N]]
        self.enemy_total[r] = float((tt.hp[tidx[N:]] + tt.sh[tidx[N:]]).sum())


class Statics:
    """What the M battles of a map share: N, E, U, team [U], map_w / map_h, loops, the
    kernels' scalars `par`, the `TypeTable` and `randomised`. For a fixed map also its
    roster as named per-unit arrays [U]: names, types, hp_max, sh_max, range, radius, kind,
    air, energy_start, smac_cd, start_pos [U, 2], healers, healable, goal [2], tidx, way_off."""

    def __init__(self, spec: MapSpec, cfg: SkirmishConfig):
        self.spec = spec
        self.N, self.E = spec.n_agents, spec.n_enemies
        self.U = self.N + self.E
        self.team = np.array([0] * self.N + [1] * self.E, np.int64)
        self.map_w, self.map_h = spec.map_size
        loop = cfg.step_mul // cfg.substeps
        self.loops = float(loop)
        self.table = TypeTable(spec, cfg, loop)
        self.randomised = spec.randomised
        per_loop = loop / LOOPS_PER_SECOND
        par = np.zeros(K.N_PAR)
        par[K.P_LOOPS], par[K.P_MAP_W], par[K.P_MAP_H] = loop, self.map_w, self.map_h
        par[K.P_REGEN_DELAY] = cfg.shield_regen_delay_s * LOOPS_PER_SECOND
        par[K.P_REGEN] = cfg.shield_regen_per_s * per_loop
        par[K.P_ACQUIRE], par[K.P_ARRIVE] = cfg.acquire_range, ARRIVE_RADIUS
        par[K.P_DODGE] = cfg.bane_dodge
        self.par = par
        if not self.randomised:
            self._fixed_roster(spec)

    def _fixed_roster(self, spec: MapSpec) -> None:
        a_names, a_pos = ordered_units(spec, "allies")
        e_names, e_pos = ordered_units(spec, "enemies")
        self.names = a_names + e_names
        self.tidx = np.array([self.table.index[n] for n in self.names], np.int64)
        ut = [unit_types()[n] for n in self.names]
        self.types = ut
        self.hp_max = np.array([t.hp for t in ut], np.float64)
        self.sh_max = np.array([t.shield for t in ut], np.float64)
        self.range = np.array([t.range for t in ut], np.float64)
        self.radius = np.array([t.radius for t in ut], np.float64)
        self.kind = np.array([KINDS.index(t.kind) for t in ut])
        self.air = np.array(["air" in t.attributes for t in ut])
        self.energy_start = np.array([t.energy_start for t in ut], np.float64)
        self.smac_cd = np.array([t.smac_max_cooldown for t in ut], np.float64)
        self.start_pos = np.concatenate([a_pos, e_pos])
        self.healers = np.flatnonzero(self.kind == HEALER)
        self.healable = ~self.air & (self.kind != HEALER)
        self.way_off = np.zeros((self.U, 2))
        self.way_off[self.N :] = e_pos - e_pos.mean(0)
        point = spec.attack_point
        goal = np.array(point) if point is not None else self.start_pos[: self.N].mean(0)
        self.goal = np.asarray(goal, np.float64)


def draw_roster(st: Statics, rng: np.random.Generator) -> tuple:
    """One episode's roster of a randomised map: (tidx [U], start_pos [U, 2], way_off [U, 2],
    goal [2]). Agents are ordered by (type name, x, y) as SMAC/SMACv2 order theirs (SC2's
    unit ids of the agents' types are alphabetical); enemies keep their creation order."""
    spec, tt, N, E = st.spec, st.table, st.N, st.E
    if spec.team_gen is not None:
        a_names, e_names = draw_teams(spec.team_gen, rng)
    else:
        a_names = [g.type for g in spec.allies for _ in range(g.count)]
        e_names = [g.type for g in spec.enemies for _ in range(g.count)]
    if spec.start_positions is not None:
        a_pts, e_pts, group = draw_points(spec.start_positions, N, E, st.map_w, st.map_h, rng)
    else:  # team_gen alone: SMACv2's two fixed points, a quarter of the map from each side
        a_pts = np.tile([st.map_w / 4, st.map_h / 2], (N, 1))
        e_pts = np.tile([3 * st.map_w / 4, st.map_h / 2], (E, 1))
        group = np.zeros(E, np.int64)
    tidx = np.array([tt.index[n] for n in a_names + e_names], np.int64)
    pos = place(np.concatenate([a_pts, e_pts]), tt.radius[tidx], tt.air[tidx], spec.map_size)
    order = sorted(range(N), key=lambda i: (a_names[i], pos[i, 0], pos[i, 1]))
    perm = np.array(order + list(range(N, N + E)))
    tidx, pos = tidx[perm], pos[perm]
    way_off = np.zeros((N + E, 2))
    size = np.bincount(group)[:, None]
    centre = np.stack([np.bincount(group, weights=pos[N:, k]) for k in (0, 1)], 1)
    way_off[N:] = pos[N:] - centre[group] / np.maximum(size[group], 1)
    point = spec.attack_point
    goal = np.array(point, np.float64) if point is not None else pos[:N].mean(0)
    return tidx, pos, way_off, goal


class Battle:
    """Dynamic state of M battles of one map.

    Storage: f [M, N_F, U] float64 and g [M, N_G, U] int64 (kernels.py), alive [M, U] bool,
    way [M, 2] the agents' spawn (the enemy's attack-move goal), rosters (`Rosters`) and rid
    [M] (battle m's roster row). Named views, all [M, U]: x, y, hp, sh, cd, energy,
    since_dmg, order, order_tgt (target unit index, -1 none), last_tgt (whom each unit
    attacked or healed in the last sub-step, -1 none), last_fire; kind (unit kinds).
    """

    def __init__(self, st: Statics, cfg: SkirmishConfig, num_envs: int):
        self.st, self.cfg, self.M = st, cfg, num_envs
        self.f = np.zeros((num_envs, K.N_F, st.U))
        self.g = np.zeros((num_envs, K.N_G, st.U), np.int64)
        self.alive = np.zeros((num_envs, st.U), bool)
        self.way = np.zeros((num_envs, 2))
        self._before = np.zeros((num_envs, 4))
        self.rosters = Rosters(st, num_envs if st.randomised else 1)
        if st.randomised:
            self.rid = np.arange(num_envs, dtype=np.int64)
        else:
            self.rid = np.zeros(num_envs, np.int64)
            self.rosters.set(0, st.tidx, st.start_pos, st.way_off, st.goal)

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
    kind = property(lambda self: self.rosters.ui[self.rid, :, K.KIND])

    def roster(self, m: int) -> SimpleNamespace:
        """Battle m's units [U]: names, kind, team, radius, hp_max, sh_max, smac_cd, onehot
        [U, bits], and the agents' sight / shoot [N] and healer flags."""
        ro, tt, r = self.rosters, self.st.table, int(self.rid[m])
        t = ro.tidx[r]
        return SimpleNamespace(
            names=[tt.names[k] for k in t], kind=tt.kind[t], team=self.st.team,
            radius=tt.radius[t], hp_max=tt.hp[t], sh_max=tt.sh[t], smac_cd=tt.smac_cd[t],
            onehot=ro.onehot[r], sight=ro.sight[r], shoot=ro.shoot[r], healer=ro.agent_healer[r],
        )  # fmt: skip

    def reset(self, envs: np.ndarray, rngs: list[np.random.Generator]) -> None:
        """Put battles `envs` (indices) at their start. A randomised map first draws each
        battle's roster from its generator; a fixed map jitters its one formation per battle:
        each side's formation shifts as a whole, units move a little within it."""
        st, cfg = self.st, self.cfg
        envs = np.asarray(envs, np.int64).reshape(-1)
        if st.randomised:
            for m in envs.tolist():
                self.rosters.set(m, *draw_roster(st, rngs[m]))
            jitter = np.array([0.0, 0.0, st.map_w - 1e-3, st.map_h - 1e-3])
        else:
            jitter = np.array([cfg.start_jitter, cfg.unit_jitter, st.map_w - 1e-3, st.map_h - 1e-3])
        draws = np.empty((envs.size, 4 + 2 * st.U))
        for r, m in enumerate(envs.tolist()):
            draws[r] = rngs[m].random(4 + 2 * st.U)
        ro = self.rosters
        step_kernels.reset_battles(envs, draws, jitter, self.rid, ro.start_pos, ro.goal, st.team,
                                   ro.uf, ro.energy_start, self.f, self.g, self.alive,
                                   self.way)  # fmt: skip

    def step(self, active: np.ndarray) -> np.ndarray:
        """Advance the `active` [M] battles by one agent step (all sub-steps).

        Returns [M, 4]: each battle's (enemy health + shields, ally health + shields, dead
        enemies, dead allies) before the step (rows of inactive battles are stale).
        """
        st, ro = self.st, self.rosters
        K.advance(
            active, self.cfg.substeps, st.N, st.par, self.rid, ro.uf, ro.ui, ro.hit, ro.can_hit,
            ro.collide, self.f, self.g, self.alive, self.way, self._before,
        )  # fmt: skip
        return self._before

    def pairwise(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """dx, dy, dist [M, U, U] with dx[m, i, j] = x_j - x_i (for scripts and tests)."""
        x, y = np.ascontiguousarray(self.x), np.ascontiguousarray(self.y)
        dx = x[:, None, :] - x[:, :, None]
        dy = y[:, None, :] - y[:, :, None]
        return dx, dy, np.sqrt(dx * dx + dy * dy)

"""SMAC's tensors, batched: available actions, observations and the global state.

Layouts follow oxwhirl SMAC's defaults (obs_all_health, no last action in the observation,
last actions in the state):

* avail [M, N, 6 + E]: 0 no-op (only, and always, when dead), 1 stop, 2-5 move N/S/E/W when
  the point `move_amount / 2` away is on the map, 6 + j attack enemy j within shoot range
  (a healer: heal ally j, never another healer).
* obs [M, N, obs_dim] (zeros when dead): 4 move flags; per enemy [attackable, dist, dx, dy,
  health, (shield), type one-hot] (zeros beyond sight range); per other ally [visible, dist, dx,
  dy, health, (shield), type one-hot]; own [health, (shield), type one-hot]. Distances / sight.
* state [M, state_dim]: per agent [health, cooldown (healer: energy), x, y, (shield), type],
  per enemy [health, x, y, (shield), type] (positions relative to the map centre over the map
  size), then every agent's last action one-hot.
"""

from __future__ import annotations

import numpy as np

from actors.envs.skirmish.sim import Battle, Statics
from actors.envs.skirmish.spec import MapSpec, SkirmishConfig


class Layout:
    """Feature sizes and static per-unit feature blocks of one map."""

    def __init__(self, spec: MapSpec, st: Statics, cfg: SkirmishConfig):
        N, E = st.N, st.E
        self.N, self.E = N, E
        self.n_actions = 6 + E
        self.bits = spec.unit_type_bits
        self.sh_ally = int(st.sh_max[:N].max() > 0)
        self.sh_enemy = int(st.sh_max[N:].max() > 0)
        self.nf_en = 5 + self.sh_enemy + self.bits
        self.nf_al = 5 + self.sh_ally + self.bits
        self.nf_own = 1 + self.sh_ally + self.bits
        self.obs_dim = 4 + E * self.nf_en + (N - 1) * self.nf_al + self.nf_own
        self.nf_al_state = 4 + self.sh_ally + self.bits
        self.nf_en_state = 3 + self.sh_enemy + self.bits
        last = N * self.n_actions if cfg.state_last_action else 0
        self.state_dim = N * self.nf_al_state + E * self.nf_en_state + last
        self.onehot = np.zeros((st.U, self.bits), np.float32)
        if self.bits:
            for u, name in enumerate(st.names):
                order = spec.ally_types if u < N else spec.enemy_types
                self.onehot[u, order.index(name)] = 1.0
        self.others = np.array([[j for j in range(N) if j != i] for i in range(N)], np.int64)
        self.others = self.others.reshape(N, N - 1)
        self.rows = np.arange(N)[:, None]
        self.agent_healer = np.isin(np.arange(N), st.healers)
        self.sh_norm = np.where(st.sh_max > 0, 1.0 / np.maximum(st.sh_max, 1e-9), 0.0)
        self.cd_norm = 1.0 / st.smac_cd


def avail_actions(b: Battle, lay: Layout, cfg: SkirmishConfig, dist: np.ndarray) -> np.ndarray:
    """Available actions [M, N, 6 + E] (uint8) of the current state."""
    st, N, M = b.st, lay.N, b.M
    alive = b.alive[:, :N]
    avail = np.zeros((M, N, lay.n_actions), np.uint8)
    avail[:, :, 0] = ~alive
    avail[:, :, 1] = alive
    half = cfg.move_amount / 2
    x, y = b.x[:, :N], b.y[:, :N]
    # SMAC truncates the probe point to a cell and checks it lies on the map.
    avail[:, :, 2] = alive & (np.trunc(y + half) < st.map_h)
    avail[:, :, 3] = alive & (np.trunc(y - half) >= 0)
    avail[:, :, 4] = alive & (np.trunc(x + half) < st.map_w)
    avail[:, :, 5] = alive & (np.trunc(x - half) >= 0)
    reach = dist[:, :N, N:] <= cfg.shoot_range
    avail[:, :, 6:] = alive[:, :, None] & b.alive[:, None, N:] & reach
    if lay.agent_healer.any():
        h = np.flatnonzero(lay.agent_healer)
        heal = dist[:, h, :N] <= cfg.shoot_range
        heal &= b.alive[:, None, :N] & st.healable[None, None, :N] & alive[:, h, None]
        avail[:, h, 6:] = 0
        k = min(N, lay.E)  # SMAC has 6 + n_enemies actions: a healer reaches allies < E
        avail[:, h, 6 : 6 + k] = heal[..., :k]
    return avail


def observations(
    b: Battle, lay: Layout, cfg: SkirmishConfig, avail: np.ndarray, dx, dy, dist
) -> np.ndarray:
    """Observations [M, N, obs_dim] (float32); see the module docstring for the layout."""
    st, N, E, M = b.st, lay.N, lay.E, b.M
    inv = 1.0 / cfg.sight_range
    alive = b.alive[:, :N]
    health = b.hp / st.hp_max
    out = np.zeros((M, N, lay.obs_dim), np.float32)
    out[:, :, :4] = avail[:, :, 2:6]
    # Enemies: one [M, N, E, nf_en] view into `out`, filled feature by feature.
    en = out[:, :, 4 : 4 + E * lay.nf_en].reshape(M, N, E, lay.nf_en)
    de = dist[:, :N, N:]
    en[..., 0] = avail[:, :, 6 : 6 + E]
    en[..., 1] = de * inv
    en[..., 2] = dx[:, :N, N:] * inv
    en[..., 3] = dy[:, :N, N:] * inv
    en[..., 4] = health[:, None, N:]
    if lay.sh_enemy:
        en[..., 5] = (b.sh[:, N:] * lay.sh_norm[N:])[:, None, :]
    if lay.bits:
        en[..., 5 + lay.sh_enemy :] = lay.onehot[N:]
    en *= ((de < cfg.sight_range) & b.alive[:, None, N:] & alive[:, :, None])[..., None]
    if N > 1:
        a0 = 4 + E * lay.nf_en
        al = out[:, :, a0 : a0 + (N - 1) * lay.nf_al].reshape(M, N, N - 1, lay.nf_al)
        rows, o = lay.rows, lay.others
        da = dist[:, rows, o]
        al[..., 0] = 1.0
        al[..., 1] = da * inv
        al[..., 2] = dx[:, rows, o] * inv
        al[..., 3] = dy[:, rows, o] * inv
        al[..., 4] = health[:, o]
        if lay.sh_ally:
            al[..., 5] = b.sh[:, o] * lay.sh_norm[o]
        if lay.bits:
            al[..., 5 + lay.sh_ally :] = lay.onehot[o]
        al *= ((da < cfg.sight_range) & b.alive[:, o] & alive[:, :, None])[..., None]
    own = out[:, :, lay.obs_dim - lay.nf_own :]
    own[..., 0] = health[:, :N]
    if lay.sh_ally:
        own[..., 1] = b.sh[:, :N] * lay.sh_norm[:N]
    if lay.bits:
        own[..., 1 + lay.sh_ally :] = lay.onehot[:N]
    out *= alive[:, :, None]
    return out


def global_state(b: Battle, lay: Layout, last_action: np.ndarray | None) -> np.ndarray:
    """Global state [M, state_dim] (float32); `last_action` [M, N, A] one-hot or None."""
    st, N, M = b.st, lay.N, b.M
    cx, cy = st.map_w / 2, st.map_h / 2
    health = b.hp / st.hp_max
    rx, ry = (b.x - cx) / st.map_w, (b.y - cy) / st.map_h
    cool = np.where(lay.agent_healer, b.energy[:, :N], b.cd[:, :N]) * lay.cd_norm[:N]
    al = [health[:, :N], cool, rx[:, :N], ry[:, :N]]
    if lay.sh_ally:
        al.append(b.sh[:, :N] * lay.sh_norm[:N])
    al_f = np.stack(al, -1)
    en = [health[:, N:], rx[:, N:], ry[:, N:]]
    if lay.sh_enemy:
        en.append(b.sh[:, N:] * lay.sh_norm[N:])
    en_f = np.stack(en, -1)
    if lay.bits:
        al_f = np.concatenate([al_f, np.broadcast_to(lay.onehot[:N], (M, N, lay.bits))], -1)
        en_f = np.concatenate([en_f, np.broadcast_to(lay.onehot[N:], (M, lay.E, lay.bits))], -1)
    al_f = al_f * b.alive[:, :N, None]
    en_f = en_f * b.alive[:, N:, None]
    parts = [al_f.reshape(M, -1), en_f.reshape(M, -1)]
    if last_action is not None:
        parts.append(last_action.reshape(M, -1))
    return np.concatenate(parts, -1).astype(np.float32)

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

Each tensor is one numba kernel over all M battles writing into a fresh array.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from actors.envs.skirmish.kernels import CD, EN, HP, SH, X, Y
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
        self.onehot = np.zeros((st.U, self.bits), np.float64)
        if self.bits:
            for u, name in enumerate(st.names):
                order = spec.ally_types if u < N else spec.enemy_types
                self.onehot[u, order.index(name)] = 1.0
        self.agent_healer = np.isin(np.arange(N), st.healers)
        self.sh_norm = np.where(st.sh_max > 0, 1.0 / np.maximum(st.sh_max, 1e-9), 0.0)
        self.cd_norm = 1.0 / st.smac_cd
        # Per-unit feature constants for the kernels: 1 / max health, shield norm (0: none).
        self.inv_hp = 1.0 / st.hp_max
        self.sizes = np.array([self.nf_en, self.nf_al, self.sh_enemy, self.sh_ally, self.bits])


def avail_actions(b: Battle, lay: Layout, cfg: SkirmishConfig) -> np.ndarray:
    """Available actions [M, N, 6 + E] (uint8) of the current state."""
    out = np.zeros((b.M, lay.N, lay.n_actions), np.uint8)
    st = b.st
    _avail_kernel(
        lay.N, lay.E, cfg.move_amount / 2, cfg.shoot_range, st.map_w, st.map_h,
        lay.agent_healer, st.healable, b.f, b.alive, out,
    )  # fmt: skip
    return out


def observations(b: Battle, lay: Layout, cfg: SkirmishConfig, avail: np.ndarray) -> np.ndarray:
    """Observations [M, N, obs_dim] (float32); see the module docstring for the layout."""
    out = np.zeros((b.M, lay.N, lay.obs_dim), np.float32)
    _obs_kernel(
        lay.N, lay.E, cfg.sight_range, lay.sizes, lay.onehot, lay.inv_hp, lay.sh_norm,
        b.f, b.alive, avail, out,
    )  # fmt: skip
    return out


def global_state(b: Battle, lay: Layout, last_action: np.ndarray | None) -> np.ndarray:
    """Global state [M, state_dim] (float32); `last_action` [M, N, A] one-hot or None."""
    out = np.zeros((b.M, lay.state_dim), np.float32)
    st = b.st
    cool_norm = np.where(lay.agent_healer, -lay.cd_norm[: lay.N], lay.cd_norm[: lay.N])
    _state_kernel(
        lay.N, lay.E, st.map_w, st.map_h, lay.sizes, lay.onehot, lay.inv_hp, lay.sh_norm,
        cool_norm, b.f, b.alive, out,
    )  # fmt: skip
    if last_action is not None:
        out[:, lay.state_dim - last_action[0].size :] = last_action.reshape(b.M, -1)
    return out


@njit(cache=True)
def _avail_kernel(N, E, half, shoot, map_w, map_h, agent_healer, healable, f, alive, out):
    M = alive.shape[0]
    k = min(N, E)  # SMAC has 6 + n_enemies actions: a healer reaches allies < E
    for m in range(M):
        for i in range(N):
            if not alive[m, i]:
                out[m, i, 0] = 1
                continue
            x, y = f[m, X, i], f[m, Y, i]
            out[m, i, 1] = 1
            # SMAC truncates the probe point to a cell and checks it lies on the map.
            out[m, i, 2] = math.trunc(y + half) < map_h
            out[m, i, 3] = math.trunc(y - half) >= 0
            out[m, i, 4] = math.trunc(x + half) < map_w
            out[m, i, 5] = math.trunc(x - half) >= 0
            lo, hi = (0, k) if agent_healer[i] else (N, N + E)
            for u in range(lo, hi):
                if not alive[m, u] or (agent_healer[i] and not healable[u]):
                    continue
                dx, dy = f[m, X, u] - x, f[m, Y, u] - y
                if math.sqrt(dx * dx + dy * dy) <= shoot:
                    out[m, i, 6 + u - lo] = 1


@njit(cache=True)
def _unit_feats(out, o, m, u, f, inv_hp, sh_norm, has_sh, onehot, bits):
    """health, (shield), type one-hot of unit u at out[o:]; returns the next offset."""
    out[o] = f[m, HP, u] * inv_hp[u]
    o += 1
    if has_sh:
        out[o] = f[m, SH, u] * sh_norm[u]
        o += 1
    for k in range(bits):
        out[o + k] = onehot[u, k]
    return o + bits


@njit(cache=True)
def _other(o_, p, m, i, v, flag, inv, sight, f, alive, inv_hp, sh_norm, has_sh, onehot, bits):
    """[flag, dist, dx, dy, health, (shield), type] of unit v seen by i at o_[p:], if seen."""
    dx, dy = f[m, X, v] - f[m, X, i], f[m, Y, v] - f[m, Y, i]
    d = math.sqrt(dx * dx + dy * dy)
    if alive[m, v] and d < sight:
        o_[p] = flag
        o_[p + 1] = d * inv
        o_[p + 2] = dx * inv
        o_[p + 3] = dy * inv
        _unit_feats(o_, p + 4, m, v, f, inv_hp, sh_norm, has_sh, onehot, bits)


@njit(cache=True)
def _obs_kernel(N, E, sight, sizes, onehot, inv_hp, sh_norm, f, alive, avail, out):
    M = alive.shape[0]
    nf_en, nf_al, sh_en, sh_al, bits = sizes[0], sizes[1], sizes[2], sizes[3], sizes[4]
    inv = 1.0 / sight
    a0 = 4 + E * nf_en
    for m in range(M):
        for i in range(N):
            if not alive[m, i]:
                continue
            o_ = out[m, i]
            for k in range(4):
                o_[k] = avail[m, i, 2 + k]
            for j in range(E):
                flag = avail[m, i, 6 + j]
                _other(o_, 4 + j * nf_en, m, i, N + j, flag, inv, sight, f, alive, inv_hp,
                       sh_norm, sh_en, onehot, bits)  # fmt: skip
            for k in range(N - 1):
                v = k + (k >= i)
                _other(o_, a0 + k * nf_al, m, i, v, 1.0, inv, sight, f, alive, inv_hp,
                       sh_norm, sh_al, onehot, bits)  # fmt: skip
            _unit_feats(o_, a0 + (N - 1) * nf_al, m, i, f, inv_hp, sh_norm, sh_al, onehot, bits)


@njit(cache=True)
def _state_kernel(N, E, map_w, map_h, sizes, onehot, inv_hp, sh_norm, cool_norm, f, alive, out):
    M = alive.shape[0]
    sh_en, sh_al, bits = sizes[2], sizes[3], sizes[4]
    nf_al, nf_en = 4 + sh_al + bits, 3 + sh_en + bits
    cx, cy = map_w / 2, map_h / 2
    for m in range(M):
        s = out[m]
        for u in range(N + E):
            if not alive[m, u]:
                continue
            enemy = u >= N
            o = N * nf_al + (u - N) * nf_en if enemy else u * nf_al
            s[o] = f[m, HP, u] * inv_hp[u]
            o += 1
            if not enemy:  # cool_norm < 0 marks a healer: its energy stands in
                c = cool_norm[u]
                s[o] = f[m, EN, u] * -c if c < 0 else f[m, CD, u] * c
                o += 1
            s[o] = (f[m, X, u] - cx) / map_w
            s[o + 1] = (f[m, Y, u] - cy) / map_h
            o += 2
            has_sh = sh_en if enemy else sh_al
            if has_sh:
                s[o] = f[m, SH, u] * sh_norm[u]
                o += 1
            for k in range(bits):
                s[o + k] = onehot[u, k]

"""SMAC's tensors, batched: available actions, observations and the global state.

Layouts follow oxwhirl SMAC's defaults (obs_all_health, no last action in the observation,
last actions in the state); `variants.py` derives SMAC's other keyword layouts from these:

* avail [M, N, 6 + E]: 0 no-op (only, and always, when dead), 1 stop, 2-5 move N/S/E/W when
  the point `move_amount / 2` away is on the map, 6 + j attack enemy j within shoot range
  (a healer: heal ally j, never another healer).
* obs [M, N, obs_dim] (zeros when dead): 4 move flags; per enemy [attackable, dist, dx, dy,
  health, (shield), type one-hot] (zeros beyond sight range); per other ally [visible, dist, dx,
  dy, health, (shield), type one-hot]; own [health, (shield), (x, y), type one-hot]. Distances
  / sight. The own position (over the map size) only on maps with `obs_own_pos` (SMACv2).
* state [M, state_dim]: per agent [health, cooldown (healer: energy), x, y, (shield), type],
  per enemy [health, x, y, (shield), type] (positions relative to the map centre over the map
  size), then every agent's last action one-hot.

Sight and shoot range are SMAC's 9 and 6, or on maps with `unit_ranges` each agent's own
(SMACv2's use_unit_ranges). Each tensor is one numba kernel over all M battles writing into
a fresh array; per-unit constants come from each battle's roster (`sim.Rosters`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from actors.envs.skirmish.config import SkirmishConfig
from actors.envs.skirmish.kernels import CD, EN, HP, SH, X, Y
from actors.envs.skirmish.sim import Battle, Statics
from actors.envs.skirmish.spec import MapSpec


class Layout:
    """Feature sizes of one map's default (SMAC-default) tensors.

    obs_dim / state_dim are these base sizes; `variants.Variant` gives the sizes under
    SMAC's other keywords. nf_en / nf_al / nf_own: features per enemy, other ally and own
    block of an observation; nf_al_state / nf_en_state: per agent and enemy in the state.
    """

    def __init__(self, spec: MapSpec, st: Statics, cfg: SkirmishConfig):
        N, E = st.N, st.E
        self.N, self.E = N, E
        self.n_actions = 6 + E
        self.bits = spec.unit_type_bits
        tt = st.table
        self.sh_ally = int(max(tt.sh[tt.index[n]] for n in spec.side_pool("allies")) > 0)
        self.sh_enemy = int(max(tt.sh[tt.index[n]] for n in spec.side_pool("enemies")) > 0)
        self.own_pos = int(spec.own_pos)
        self.nf_en = 5 + self.sh_enemy + self.bits
        self.nf_al = 5 + self.sh_ally + self.bits
        self.nf_own = 1 + self.sh_ally + 2 * self.own_pos + self.bits
        self.obs_dim = 4 + E * self.nf_en + (N - 1) * self.nf_al + self.nf_own
        self.nf_al_state = 4 + self.sh_ally + self.bits
        self.nf_en_state = 3 + self.sh_enemy + self.bits
        last = N * self.n_actions if cfg.state_last_action else 0
        self.state_dim = N * self.nf_al_state + E * self.nf_en_state + last
        self.sizes = np.array(
            [self.nf_en, self.nf_al, self.sh_enemy, self.sh_ally, self.bits, self.own_pos]
        )


def avail_actions(b: Battle, lay: Layout, cfg: SkirmishConfig) -> np.ndarray:
    """Available actions [M, N, 6 + E] (uint8) of the current state."""
    out = np.zeros((b.M, lay.N, lay.n_actions), np.uint8)
    st, ro = b.st, b.rosters
    _avail_kernel(
        lay.N, lay.E, cfg.move_amount / 2, b.rid, ro.shoot, st.map_w, st.map_h,
        ro.agent_healer, ro.healable, b.f, b.alive, out,
    )  # fmt: skip
    return out


def observations(b: Battle, lay: Layout, avail: np.ndarray) -> np.ndarray:
    """Observations [M, N, obs_dim] (float32); see the module docstring for the layout."""
    out = np.zeros((b.M, lay.N, lay.obs_dim), np.float32)
    st, ro = b.st, b.rosters
    _obs_kernel(
        lay.N, lay.E, b.rid, ro.sight, lay.sizes, ro.onehot, ro.inv_hp, ro.sh_norm,
        st.map_w, st.map_h, b.f, b.alive, avail, out,
    )  # fmt: skip
    return out


def global_state(b: Battle, lay: Layout, last_action: np.ndarray | None) -> np.ndarray:
    """Global state [M, state_dim] (float32); `last_action` [M, N, A] one-hot or None."""
    out = np.zeros((b.M, lay.state_dim), np.float32)
    st, ro = b.st, b.rosters
    _state_kernel(
        lay.N, lay.E, st.map_w, st.map_h, lay.sizes, b.rid, ro.onehot, ro.inv_hp, ro.sh_norm,
        ro.cool_norm, b.f, b.alive, out,
    )  # fmt: skip
    if last_action is not None:
        out[:, lay.state_dim - last_action[0].size :] = last_action.reshape(b.M, -1)
    return out


@njit(cache=True)
def _avail_kernel(N, E, half, rid, shoots, map_w, map_h, agent_healers, healables, f, alive,
                  out):  # fmt: skip
    M = alive.shape[0]
    k = min(N, E)  # SMAC has 6 + n_enemies actions: a healer reaches allies < E
    for m in range(M):
        r = rid[m]
        shoot, agent_healer, healable = shoots[r], agent_healers[r], healables[r]
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
                if math.sqrt(dx * dx + dy * dy) <= shoot[i]:
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
def _obs_kernel(N, E, rid, sights, sizes, onehots, inv_hps, sh_norms, map_w, map_h, f, alive,
                avail, out):  # fmt: skip
    M = alive.shape[0]
    nf_en, nf_al, sh_en, sh_al, bits = sizes[0], sizes[1], sizes[2], sizes[3], sizes[4]
    a0 = 4 + E * nf_en
    for m in range(M):
        r = rid[m]
        onehot, inv_hp, sh_norm = onehots[r], inv_hps[r], sh_norms[r]
        for i in range(N):
            if not alive[m, i]:
                continue
            sight = sights[r, i]
            inv = 1.0 / sight
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
            o = a0 + (N - 1) * nf_al
            if sizes[5]:  # own position: health, (shield), x, y, type
                o = _unit_feats(o_, o, m, i, f, inv_hp, sh_norm, sh_al, onehot, 0)
                o_[o] = f[m, X, i] / map_w
                o_[o + 1] = f[m, Y, i] / map_h
                for k in range(bits):
                    o_[o + 2 + k] = onehot[i, k]
            else:
                _unit_feats(o_, o, m, i, f, inv_hp, sh_norm, sh_al, onehot, bits)


@njit(cache=True)
def _state_kernel(N, E, map_w, map_h, sizes, rid, onehots, inv_hps, sh_norms, cool_norms, f,
                  alive, out):  # fmt: skip
    M = alive.shape[0]
    sh_en, sh_al, bits = sizes[2], sizes[3], sizes[4]
    nf_al, nf_en = 4 + sh_al + bits, 3 + sh_en + bits
    cx, cy = map_w / 2, map_h / 2
    for m in range(M):
        r = rid[m]
        onehot, inv_hp, sh_norm, cool_norm = onehots[r], inv_hps[r], sh_norms[r], cool_norms[r]
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

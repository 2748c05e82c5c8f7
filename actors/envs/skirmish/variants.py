"""SMAC's optional observation and state keywords, as a column map over the default layout.

`views.py` computes SMAC's default tensors. oxwhirl SMAC's `StarCraft2Env` keywords change
them as follows, and `Variant` does the same to the default tensors (no copy when every
keyword has its default):

* obs_all_health=False: no health / shield in the enemy and ally blocks; the own block
  keeps them only with obs_own_health (obs_all_health=True implies obs_own_health).
* obs_last_action: each other-ally block ends with that ally's last action one-hot
  (n_actions), filled only while the ally is visible.
* obs_timestep_number: every observation (a dead agent's too) ends with step / limit.
  SMAC counts this element in `get_obs_size()`, but its `get_obs_agent` returns one element
  more (an unused zero in the own block, then the step); skirmish returns exactly the size
  `get_obs_size()` reports, with the step last, as SMACv2 does.
* obs_instead_of_state: the state is the agents' observations concatenated (then
  state_last_action and state_timestep_number do not apply, as in SMAC).
* state_last_action=False drops the last actions from the state (done in `views.py`);
  state_timestep_number appends step / limit to it.

Shapes: obs [M, N, obs_dim]; state [M, state_dim]; last_action [M, N, n_actions]; t [M].
"""

from __future__ import annotations

import numpy as np

from actors.envs.skirmish.config import SkirmishConfig
from actors.envs.skirmish.views import Layout


class Variant:
    """The observation / state layout a `SkirmishConfig` asks for, over `lay`'s default one.

    Attributes:
        obs_dim / state_dim: the sizes under the config's keywords.
        active: whether the observation differs from the default layout.
    """

    def __init__(self, lay: Layout, cfg: SkirmishConfig, episode_limit: int):
        N, E, A = lay.N, lay.E, lay.n_actions
        self.cfg, self.limit, self.A = cfg, float(episode_limit), A
        health = cfg.obs_all_health
        src: list[int] = list(range(4))
        for j in range(E):
            b = 4 + j * lay.nf_en
            src += self._block(b, lay.sh_enemy, lay.bits, health)
        a0 = 4 + E * lay.nf_en
        self.vis_cols = np.array([a0 + k * lay.nf_al for k in range(N - 1)], np.int64)
        la_idx = []
        for k in range(N - 1):
            src += self._block(int(self.vis_cols[k]), lay.sh_ally, lay.bits, health)
            if cfg.obs_last_action:
                la_idx += range(len(src), len(src) + A)
                src += [-1] * A
        own = a0 + (N - 1) * lay.nf_al
        n_health = 1 + lay.sh_ally
        if cfg.own_health:
            src += range(own, own + n_health)
        src += range(own + n_health, own + lay.nf_own)
        if cfg.obs_timestep_number:
            src.append(-1)
        self.src = np.array(src, np.int64)
        self.la_idx = np.array(la_idx, np.int64)
        self.active = not np.array_equal(self.src, np.arange(lay.obs_dim))
        self.obs_dim = len(src)
        ids = np.arange(N - 1)
        self.ally_ids = ids[None, :] + (ids[None, :] >= np.arange(N)[:, None])  # [N, N - 1]
        if cfg.obs_instead_of_state:
            self.state_dim = N * self.obs_dim
        else:
            self.state_dim = lay.state_dim + int(cfg.state_timestep_number)

    @staticmethod
    def _block(b: int, shield: int, bits: int, health: bool) -> list[int]:
        """Columns of one enemy / ally block [flag, dist, dx, dy, health, (shield), type]."""
        cols = list(range(b, b + 4))
        if health:
            cols += range(b + 4, b + 5 + shield)
        return cols + list(range(b + 5 + shield, b + 5 + shield + bits))

    def obs(self, base: np.ndarray, last_action: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Observations [M, N, obs_dim] from the default ones `base` [M, N, D]."""
        if not self.active:
            return base
        out = base[:, :, np.maximum(self.src, 0)]
        out[:, :, self.src < 0] = 0.0
        if self.la_idx.size:
            M, N = base.shape[:2]
            vis = base[:, :, self.vis_cols]  # [M, N, N - 1]
            la = last_action[:, self.ally_ids] * vis[..., None]
            out[:, :, self.la_idx] = la.reshape(M, N, -1)
        if self.cfg.obs_timestep_number:
            out[:, :, -1] = (t / self.limit)[:, None]
        return out

    def state(self, base: np.ndarray, obs: np.ndarray, t: np.ndarray) -> np.ndarray:
        """The state [M, state_dim] from the default one `base` and the observations."""
        if self.cfg.obs_instead_of_state:
            return obs.reshape(obs.shape[0], -1).copy()
        if self.cfg.state_timestep_number:
            step = (t / self.limit).astype(np.float32)[:, None]
            return np.concatenate([base, step], axis=1)
        return base

"""The skirmish envs: `SkirmishVecEnv` (M battles per NumPy call, what rollout actors use)
and `SkirmishEnv` (one battle, SMAC's `StarCraft2Env` API, a drop-in for pymarl loops).

Reward, termination and statistics follow SMAC: damage dealt to enemy health and shields
plus `reward_death_value` per kill plus `reward_win` for a win, divided by
`max_reward / reward_scale_rate` where max_reward = sum of enemy health and shields +
death value x n_enemies + win reward, so a perfect episode returns 20 (SMAC's other reward
keywords: see `SkirmishConfig`). On a randomised map max_reward is each episode's own
(SMACv2 keeps the first episode's). A timeout ends the episode (terminated True) with
`info["episode_limit"] = True` and is not a win.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from actors.envs.base import EnvError, EnvInfo
from actors.envs.skirmish.config import SkirmishConfig
from actors.envs.skirmish.sim import Battle, Statics
from actors.envs.skirmish.spec import MapSpec
from actors.envs.skirmish.step_kernels import outcome, set_orders
from actors.envs.skirmish.variants import Variant
from actors.envs.skirmish.views import Layout, avail_actions, global_state, observations

log = logging.getLogger(__name__)


class SkirmishVecEnv:
    """M skirmish battles of one map stepped together (the `VecEnv` protocol).

    Args:
        spec: the map.
        num_envs: M.
        seed: env k draws its randomness from `np.random.default_rng(seed + k)`, so it plays
            exactly like `SkirmishEnv(spec, seed=seed + k)`. None: fresh entropy.
        config: simulator and SMAC options.

    Shapes: step(actions [M, N] int, active [M] bool) -> reward [M], terminated [M], M infos;
    get_obs() [M, N, obs_dim]; get_state() [M, state_dim]; get_avail_actions() [M, N, A].
    """

    def __init__(
        self,
        spec: MapSpec,
        num_envs: int,
        seed: int | None = None,
        config: SkirmishConfig | None = None,
    ):
        self.cfg = config or SkirmishConfig()
        self.cfg.validate()
        if num_envs < 1:
            raise EnvError(f"num_envs must be >= 1, got {num_envs}")
        self.spec, self.num_envs = spec, num_envs
        self.st = Statics(spec, self.cfg)
        self.lay = Layout(spec, self.st, self.cfg)
        self.variant = Variant(self.lay, self.cfg, spec.episode_limit)
        self.battle = Battle(self.st, self.cfg, num_envs)
        self.info = EnvInfo(
            n_agents=self.st.N,
            n_actions=self.lay.n_actions,
            obs_shape=self.variant.obs_dim,
            state_shape=self.variant.state_dim,
            episode_limit=spec.episode_limit,
            has_wins=True,
            n_enemies=self.st.E,
        )
        cfg = self.cfg
        self._rp = np.array(
            [cfg.reward_death_value, cfg.reward_win, cfg.reward_defeat, float(cfg.reward_scale),
             float(cfg.reward_only_positive), cfg.reward_negative_scale, float(cfg.reward_sparse)]
        )  # fmt: skip
        self.seed(seed)
        M, N = num_envs, self.st.N
        self.t = np.zeros(M, np.int64)
        self.done = np.ones(M, bool)
        self.last_action = np.zeros((M, N, self.lay.n_actions), np.float32)
        self.stats = {"battles_won": 0, "battles_game": 0, "timeouts": 0}
        self._cache: dict[str, Any] = {}

    @property
    def max_reward(self) -> np.ndarray:
        """[M] each battle's maximum episode return before scaling (SMAC's max_reward)."""
        total = self.battle.rosters.enemy_total[self.battle.rid]
        return total + self.st.E * self.cfg.reward_death_value + self.cfg.reward_win

    def seed(self, seed: int | None = None) -> None:
        """Re-seed every env's generator (env k: seed + k); applies from the next reset."""
        self._seed = seed
        self.rngs = [
            np.random.default_rng(None if seed is None else seed + k) for k in range(self.num_envs)
        ]

    def get_rng_state(self) -> list[dict]:
        """Every env's generator state (what a checkpoint keeps to replay the same episodes)."""
        return [g.bit_generator.state for g in self.rngs]

    def set_rng_state(self, state: list[dict]) -> None:
        """Restore what `get_rng_state` returned (same number of envs)."""
        if len(state) != self.num_envs:
            raise EnvError(f"rng state of {len(state)} envs for {self.num_envs} envs")
        for g, s in zip(self.rngs, state, strict=True):
            g.bit_generator.state = s

    def reset(self) -> None:
        """Start a new episode in every env."""
        envs = np.arange(self.num_envs)
        self.battle.reset(envs, self.rngs)
        self.t[:] = 0
        self.done[:] = False
        self.last_action[:] = 0
        self._cache = {}

    def reset_envs(self, envs: np.ndarray) -> None:
        """Start a new episode in the envs with indices `envs` only (the others carry on)."""
        envs = np.asarray(envs, np.int64).reshape(-1)
        self.battle.reset(envs, self.rngs)
        self.t[envs] = 0
        self.done[envs] = False
        self.last_action[envs] = 0
        self._cache = {}

    def step(
        self, actions: np.ndarray, active: np.ndarray | None = None, unchecked: bool = False
    ) -> tuple[np.ndarray, np.ndarray, list[dict[str, Any]]]:
        """Apply `actions` [M, N] in the `active` [M] envs and advance them one agent step.
        `unchecked`: give the actions as orders without checking them against the available
        actions (SMAC's heuristic_ai orders attacks on units out of range, which chase)."""
        M, N = self.num_envs, self.st.N
        active = np.ones(M, bool) if active is None else np.asarray(active, bool).reshape(M).copy()
        if (active & self.done).any():
            k = int(np.flatnonzero(active & self.done)[0])
            raise EnvError(f"env {k}: step() on a finished episode; call reset() first")
        acts = np.ascontiguousarray(actions, np.int64).reshape(M, N)
        avail = self.get_avail_actions()
        if unchecked:
            avail = np.ones_like(avail)
        b = self.battle
        bad = set_orders(acts, active, avail, N, b.rid, b.rosters.agent_healer,
                         self.cfg.move_amount, b.f, b.g, self.last_action)  # fmt: skip
        if bad >= 0:
            k, i = divmod(int(bad), N)
            valid = np.flatnonzero(avail[k, i]).tolist()
            where = f"env {k}: " if self.num_envs > 1 else ""
            raise EnvError(
                f"{where}agent {i} cannot take action {int(acts[k, i])} now; available: {valid}"
            )
        before = self.battle.step(active)
        self.t += active
        self._cache = {}
        return self._outcome(active, before)

    def _outcome(self, active: np.ndarray, before: np.ndarray):
        b, M, N = self.battle, self.num_envs, self.st.N
        reward = np.empty(M)
        term, won, timeout = np.empty(M, bool), np.empty(M, bool), np.empty(M, bool)
        ro = b.rosters
        scale = ro.enemy_total + self.st.E * self.cfg.reward_death_value + self.cfg.reward_win
        scale = scale / self.cfg.reward_scale_rate
        outcome(active, self.t, N, self.spec.episode_limit, self._rp, scale, b.rid, ro.ui, b.f,
                b.alive, before, reward, term, won, timeout)  # fmt: skip
        finished = term & active
        self.done |= finished
        self.stats["battles_game"] += int(finished.sum())
        self.stats["battles_won"] += int(won.sum())
        self.stats["timeouts"] += int(timeout.sum())
        flags = zip(won.tolist(), timeout.tolist(), active.tolist(), strict=True)
        infos = [{"battle_won": w, "episode_limit": to} if a else {} for w, to, a in flags]
        for k in np.flatnonzero(finished).tolist():
            infos[k]["dead_allies"] = int(N - b.alive[k, :N].sum())
            infos[k]["dead_enemies"] = int(self.st.E - b.alive[k, N:].sum())
        return reward.astype(np.float32), term, infos

    # -- views (cached until the next step or reset) ----------------------------------------
    def pairwise(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """dx, dy, dist [M, U, U] of the current positions (for scripts), cached per step."""
        if "pairwise" not in self._cache:
            self._cache["pairwise"] = self.battle.pairwise()
        return self._cache["pairwise"]

    def get_avail_actions(self) -> np.ndarray:
        if "avail" not in self._cache:
            self._cache["avail"] = avail_actions(self.battle, self.lay, self.cfg)
        return self._cache["avail"]

    def get_obs(self) -> np.ndarray:
        if "obs" not in self._cache:
            avail = self.get_avail_actions()
            base = observations(self.battle, self.lay, avail)
            self._cache["obs"] = self.variant.obs(base, self.last_action, self.t)
        return self._cache["obs"]

    def get_state(self) -> np.ndarray:
        if "state" not in self._cache:
            if self.cfg.obs_instead_of_state:
                base = None
            else:
                last = self.last_action if self.cfg.state_last_action else None
                base = global_state(self.battle, self.lay, last)
            obs = self.get_obs() if self.cfg.obs_instead_of_state else None
            self._cache["state"] = self.variant.state(base, obs, self.t)
        return self._cache["state"]

    def get_stats(self) -> dict[str, Any]:
        """SMAC's statistics summed over the M envs."""
        s = dict(self.stats)
        s["battles_draw"] = s["timeouts"]
        s["win_rate"] = s["battles_won"] / s["battles_game"] if s["battles_game"] else 0.0
        s["restarts"] = 0
        return s

    def close(self) -> None:
        self._cache = {}


class SkirmishEnv:
    """One skirmish battle with SMAC's `StarCraft2Env` API (a pymarl drop-in).

    Args:
        spec: the map.
        seed: seeds the start-position noise; the same seed replays the same episodes.
        config: simulator and SMAC options.

    Shapes: get_obs() [N, obs_dim]; get_state() [state_dim]; get_avail_actions() [N, A];
    step(actions [N]) -> (reward float, terminated bool, info dict).
    """

    def __init__(
        self, spec: MapSpec, seed: int | None = None, config: SkirmishConfig | None = None
    ):
        self.vec = SkirmishVecEnv(spec, 1, seed=seed, config=config)
        self.map_name = spec.name
        self.n_agents = self.vec.info.n_agents
        self.n_enemies = self.vec.info.n_enemies
        self.n_actions = self.vec.info.n_actions
        self.episode_limit = self.vec.info.episode_limit
        self._episode_steps = 0

    def reset(self) -> tuple[np.ndarray, np.ndarray]:
        self.vec.reset()
        self._episode_steps = 0
        return self.get_obs(), self.get_state()

    def step(self, actions) -> tuple[float, bool, dict[str, Any]]:
        acts = np.asarray(actions, np.int64).reshape(1, -1)
        if acts.shape[1] != self.n_agents:
            raise EnvError(f"expected {self.n_agents} actions (one per agent), got {acts.shape[1]}")
        reward, terminated, infos = self.vec.step(acts, np.ones(1, bool))
        self._episode_steps += 1
        return float(reward[0]), bool(terminated[0]), infos[0]

    def get_obs(self) -> np.ndarray:
        return self.vec.get_obs()[0]

    def get_obs_agent(self, agent_id: int) -> np.ndarray:
        return self.get_obs()[agent_id]

    def get_obs_size(self) -> int:
        return self.vec.info.obs_shape

    def get_state(self) -> np.ndarray:
        return self.vec.get_state()[0]

    def get_state_size(self) -> int:
        return self.vec.info.state_shape

    def get_avail_actions(self) -> np.ndarray:
        return self.vec.get_avail_actions()[0]

    def get_avail_agent_actions(self, agent_id: int) -> np.ndarray:
        return self.get_avail_actions()[agent_id]

    def get_total_actions(self) -> int:
        return self.n_actions

    def get_env_info(self) -> dict[str, Any]:
        d: dict[str, Any] = self.vec.info.as_smac_dict()
        d.update(n_enemies=self.n_enemies, has_wins=True, map_name=self.map_name)
        return d

    def get_stats(self) -> dict[str, Any]:
        return self.vec.get_stats()

    def seed(self, seed: int | None = None) -> int | None:
        """Re-seed (from the next reset) when `seed` is given; return the current seed."""
        if seed is not None:
            self.vec.seed(seed)
        return self.vec._seed

    def get_rng_state(self) -> list[dict]:
        return self.vec.get_rng_state()

    def set_rng_state(self, state: list[dict]) -> None:
        self.vec.set_rng_state(state)

    def render(self) -> None:
        """Use `actors.episode_gifs.render_episode` for GIFs."""

    def close(self) -> None:
        self.vec.close()

    @property
    def battle(self) -> Battle:
        return self.vec.battle

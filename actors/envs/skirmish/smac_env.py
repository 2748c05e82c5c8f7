"""`StarCraft2Env`: oxwhirl SMAC's constructor and client methods over a skirmish battle.

A drop-in for code written against `smac.env.StarCraft2Env` (PyMARL, EPyMARL, PyMARL2; see
the README's recipe): the same keywords with SMAC's defaults, the same methods and return
types (lists from `get_obs` / `get_avail_actions`, a float32 state, `info` with
`battle_won`, `dead_allies`, `dead_enemies` on every step), the same statistics.

Keywords, by what they do here:

* Honoured as SMAC does: `map_name` (a skirmish map: "3m", "skirmish/3m",
  "protoss_5_vs_5", a map file path ending in .yaml, or a `MapSpec`), `step_mul` (None:
  the default 8),
  `move_amount`, `seed`, `continuing_episode` (only then does a timeout's info carry
  `episode_limit=True`), `obs_all_health`, `obs_own_health`, `obs_last_action`,
  `obs_instead_of_state`, `obs_timestep_number`, `state_last_action`,
  `state_timestep_number`, `reward_sparse`, `reward_only_positive`, `reward_negative_scale`,
  `reward_death_value`, `reward_win`, `reward_defeat`, `reward_scale`, `reward_scale_rate`
  (layouts in `variants.py`, rewards in `config.SkirmishConfig`); `replay_dir` and
  `replay_prefix` (where `save_replay` writes its GIF); `debug` (actions and rewards are
  logged at DEBUG level); `heuristic_ai` and `heuristic_rest` (SMAC's scripted allies:
  each agent keeps attacking the nearest enemy until it dies, a marauder never picks a
  medivac, a medivac heals the nearest hurt ally; the actions passed to `step` are ignored
  and overwritten in place with the ones taken, as SMAC does; with heuristic_rest an agent
  whose target is out of range moves towards it instead). A medivac without a hurt ally
  stops (SMAC leaves its last order running).
* StarCraft II's alone, accepted and without effect: `game_version`, `window_size_x`,
  `window_size_y`, `difficulty` (checked against SMAC's levels "1"-"9", "A"; skirmish's
  enemy is one scripted attack-move AI at every level).
* Not available, an EnvError naming the keyword: `obs_pathing_grid=True` and
  `obs_terrain_height=True` (skirmish maps are open and flat: no grid, no heights).
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from actors.envs.base import EnvError
from actors.envs.skirmish.config import SkirmishConfig
from actors.envs.skirmish.env import SkirmishVecEnv
from actors.envs.skirmish.maps import builtin_map, load_map_file
from actors.envs.skirmish.multiagentenv import MultiAgentEnv
from actors.envs.skirmish.spec import MapSpec

log = logging.getLogger(__name__)
DIFFICULTIES = ("1", "2", "3", "4", "5", "6", "7", "8", "9", "A")
REPLAY_EPISODES = 10  # episodes kept for save_replay (older ones are dropped)
UNAVAILABLE = {
    "obs_pathing_grid": "skirmish maps are open fields: there is no pathing grid",
    "obs_terrain_height": "skirmish maps are flat: there are no terrain heights",
}
# The SMAC keywords that become SkirmishConfig fields under the same name.
CONFIG_KEYS = (
    "obs_all_health", "obs_own_health", "obs_last_action", "obs_instead_of_state",
    "obs_timestep_number", "state_last_action", "state_timestep_number", "reward_sparse",
    "reward_only_positive", "reward_negative_scale", "reward_death_value", "reward_win",
    "reward_defeat", "reward_scale", "reward_scale_rate", "move_amount",
)  # fmt: skip


def resolve_map(map_name: str | MapSpec) -> MapSpec:
    """A skirmish map from SMAC's `map_name`: a built-in name (optionally "skirmish/"-
    prefixed), the path of a map file ending in .yaml / .yml, or a MapSpec."""
    if isinstance(map_name, MapSpec):
        return map_name
    if not isinstance(map_name, str):
        raise EnvError(f"map_name must be a string, got {map_name!r}")
    if map_name.endswith((".yaml", ".yml")):
        return load_map_file(map_name)
    return builtin_map(map_name.removeprefix("skirmish/"))


def _substeps(step_mul: int) -> int:
    """Physics sub-steps per agent step: the fewest that keep each one <= 4 game loops."""
    return next(d for d in range(1, step_mul + 1) if step_mul % d == 0 and step_mul // d <= 4)


def make_smac_config(opts: dict[str, Any]) -> SkirmishConfig:
    """The SkirmishConfig of SMAC keyword values `opts` (all of StarCraft2Env's keywords);
    values skirmish cannot honour raise EnvError naming the keyword."""
    for key, why in UNAVAILABLE.items():
        if opts[key]:
            raise EnvError(f"{key}={opts[key]!r} is not supported: {why}; use {key}=False")
    if str(opts["difficulty"]) not in DIFFICULTIES:
        raise EnvError(
            f"difficulty must be one of {list(DIFFICULTIES)}, got {opts['difficulty']!r}"
        )
    for key in ("window_size_x", "window_size_y"):
        if not isinstance(opts[key], int | float) or opts[key] <= 0:
            raise EnvError(f"{key} must be a positive number, got {opts[key]!r}")
    step_mul = 8 if opts["step_mul"] is None else opts["step_mul"]
    if not isinstance(step_mul, int) or isinstance(step_mul, bool) or step_mul < 1:
        raise EnvError(f"step_mul must be an int >= 1 (or None for 8), got {step_mul!r}")
    vals: dict[str, Any] = {}
    for key in CONFIG_KEYS:
        v = opts[key]
        default = getattr(SkirmishConfig, key)
        if isinstance(default, bool):
            vals[key] = bool(v)
        elif not isinstance(v, int | float) or isinstance(v, bool) or not math.isfinite(v):
            raise EnvError(f"{key} must be a finite number, got {v!r}")
        else:
            vals[key] = float(v)
    cfg = SkirmishConfig(step_mul=step_mul, substeps=_substeps(step_mul), **vals)
    cfg.validate()
    return cfg


class StarCraft2Env(MultiAgentEnv):
    """oxwhirl SMAC's `StarCraft2Env` on the skirmish simulator (module docstring: keywords).

    Shapes: get_obs() list of N float32 [obs_shape]; get_state() float32 [state_shape];
    get_avail_actions() list of N lists of n_actions 0/1 ints; step(actions: N ints, e.g.
    a list, an array or a torch LongTensor) -> (reward float, terminated bool, info dict).
    """

    def __init__(
        self,
        map_name="8m",
        step_mul=8,
        move_amount=2,
        difficulty="7",
        game_version=None,
        seed=None,
        continuing_episode=False,
        obs_all_health=True,
        obs_own_health=True,
        obs_last_action=False,
        obs_pathing_grid=False,
        obs_terrain_height=False,
        obs_instead_of_state=False,
        obs_timestep_number=False,
        state_last_action=True,
        state_timestep_number=False,
        reward_sparse=False,
        reward_only_positive=True,
        reward_death_value=10,
        reward_win=200,
        reward_defeat=0,
        reward_negative_scale=0.5,
        reward_scale=True,
        reward_scale_rate=20,
        replay_dir="",
        replay_prefix="",
        window_size_x=1920,
        window_size_y=1200,
        heuristic_ai=False,
        heuristic_rest=False,
        debug=False,
    ):
        opts = {k: v for k, v in locals().items() if k not in ("self", "__class__")}
        self.options = dict(opts)
        cfg = make_smac_config(opts)
        spec = resolve_map(map_name)
        self.vec = SkirmishVecEnv(spec, 1, seed=seed, config=cfg)
        opts["map_name"] = spec.name if isinstance(map_name, MapSpec) else map_name
        self._set_attributes(opts, cfg)
        self._replays: deque[dict] = deque(maxlen=REPLAY_EPISODES)
        self._figure = None

    def _set_attributes(self, opts: dict[str, Any], cfg: SkirmishConfig) -> None:
        """SMAC's public attributes (PyMARL-family code reads some of them)."""
        for key in ("map_name", "difficulty", "game_version", "continuing_episode", "debug",
                    "heuristic_ai", "heuristic_rest", "replay_dir", "replay_prefix",
                    "obs_pathing_grid", "obs_terrain_height", *CONFIG_KEYS):  # fmt: skip
            setattr(self, key, getattr(cfg, key, opts[key]))
        self.obs_own_health = cfg.own_health
        self._seed, self._move_amount, self._step_mul = opts["seed"], cfg.move_amount, cfg.step_mul
        self.window_size = (opts["window_size_x"], opts["window_size_y"])
        info, lay = self.vec.info, self.vec.lay
        self.n_agents, self.n_enemies = info.n_agents, info.n_enemies
        self.episode_limit, self.n_actions = info.episode_limit, info.n_actions
        self.n_actions_no_attack, self.n_actions_move = 6, 4
        self.shield_bits_ally, self.shield_bits_enemy = lay.sh_ally, lay.sh_enemy
        self.unit_type_bits = lay.bits
        bits = [f"type_{k}" for k in range(lay.bits)]
        shield = ["shield"]
        self.ally_state_attr_names = ["health", "energy/cooldown", "rel_x", "rel_y"]
        self.ally_state_attr_names += shield * lay.sh_ally + bits
        self.enemy_state_attr_names = ["health", "rel_x", "rel_y", *shield * lay.sh_enemy, *bits]
        self._episode_count = self._episode_steps = self._total_steps = 0
        self.force_restarts = 0
        self.last_action = np.zeros((self.n_agents, self.n_actions))
        self.heuristic_targets: list[int | None] = [None] * self.n_agents
        self.reward = 0.0

    # -- episode -----------------------------------------------------------------------
    def reset(self) -> tuple[list[np.ndarray], np.ndarray]:
        """Start an episode; returns (get_obs(), get_state())."""
        self.vec.reset()
        self._episode_steps = 0
        self.last_action = np.zeros((self.n_agents, self.n_actions))
        self.heuristic_targets = [None] * self.n_agents
        from actors.envs.skirmish.render import dynamics, statics

        self._replays.append({"statics": statics(self.vec), "frames": [dynamics(self.vec)]})
        if self.debug:
            log.debug("started episode %d of %s", self._episode_count, self.map_name)
        return self.get_obs(), self.get_state()

    def step(self, actions) -> tuple[float, bool, dict[str, Any]]:
        """Apply one action per agent; returns (reward, terminated, info)."""
        acts = np.array([int(a) for a in actions], np.int64)
        if acts.shape != (self.n_agents,):
            raise EnvError(f"expected {self.n_agents} actions (one per agent), got {acts.size}")
        if self.heuristic_ai and not self.vec.done[0]:
            taken = self._heuristic_actions()
            with contextlib.suppress(TypeError, ValueError, IndexError):
                for i, a in enumerate(taken.tolist()):
                    actions[i] = a  # SMAC writes the heuristic's actions back
            reward, term, infos = self.vec.step(taken[None], np.ones(1, bool), unchecked=True)
        else:
            reward, term, infos = self.vec.step(acts[None], np.ones(1, bool))
        self.last_action = np.eye(self.n_actions)[acts]
        self.vec.last_action[0] = self.last_action  # SMAC's: the actions passed (heuristic_ai)
        self._episode_steps += 1
        self._total_steps += 1
        alive = self.vec.battle.alive[0]
        info: dict[str, Any] = {
            "battle_won": bool(infos[0]["battle_won"]),
            "dead_allies": int(self.n_agents - alive[: self.n_agents].sum()),
            "dead_enemies": int(self.n_enemies - alive[self.n_agents :].sum()),
        }
        if term[0]:
            self._episode_count += 1
            if infos[0]["episode_limit"] and self.continuing_episode:
                info["episode_limit"] = True
        from actors.envs.skirmish.render import dynamics

        if self._replays:
            self._replays[-1]["frames"].append(dynamics(self.vec))
        self.reward = float(reward[0])
        if self.debug:
            log.debug("step %d actions %s reward %.4f", self._episode_steps, acts.tolist(),
                      self.reward)  # fmt: skip
        return self.reward, bool(term[0]), info

    def _heuristic_actions(self) -> np.ndarray:
        """SMAC's heuristic_ai: each agent's action [N] (see the module docstring)."""
        b, N = self.vec.battle, self.n_agents
        ro, alive, hp = b.roster(0), b.alive[0], b.hp[0]
        _, _, dist = b.pairwise()
        avail = self.vec.get_avail_actions()[0]
        out = np.zeros(N, np.int64)
        for i in range(N):
            if not alive[i]:
                continue
            medivac = ro.names[i] == "medivac"
            t = self.heuristic_targets[i]
            u = None if t is None else (t if medivac else N + t)
            if u is None or not alive[u] or (medivac and hp[u] >= ro.hp_max[u]):
                if medivac:
                    ok = [v for v in range(min(N, self.n_enemies)) if ro.names[v] != "medivac"
                          and alive[v] and hp[v] < ro.hp_max[v]]  # fmt: skip
                else:
                    skip = ro.names[i] == "marauder"
                    ok = [v for v in range(N, N + self.n_enemies)
                          if alive[v] and not (skip and ro.names[v] == "medivac")]  # fmt: skip
                u = min(ok, key=lambda v: dist[0, i, v]) if ok else None
                self.heuristic_targets[i] = None if u is None else (u if medivac else u - N)
            if u is None:
                continue  # no-op: the unit stops
            a = 6 + int(self.heuristic_targets[i])
            if self.heuristic_rest and not avail[i, a]:  # out of range: move towards it
                dx, dy = b.x[0, u] - b.x[0, i], b.y[0, u] - b.y[0, i]
                a = (4 if dx > 0 else 5) if abs(dx) > abs(dy) else (2 if dy > 0 else 3)
            out[i] = a
        return out

    # -- views ---------------------------------------------------------------------------
    def get_obs(self) -> list[np.ndarray]:
        """Every agent's observation (a list of N float32 arrays, SMAC's type)."""
        return list(self.vec.get_obs()[0])

    def get_obs_agent(self, agent_id: int) -> np.ndarray:
        return self.vec.get_obs()[0, agent_id]

    def get_obs_size(self) -> int:
        return self.vec.info.obs_shape

    def get_state(self) -> np.ndarray:
        return self.vec.get_state()[0]

    def get_state_size(self) -> int:
        return self.vec.info.state_shape

    def get_avail_actions(self) -> list[list[int]]:
        return self.vec.get_avail_actions()[0].astype(int).tolist()

    def get_avail_agent_actions(self, agent_id: int) -> list[int]:
        return self.vec.get_avail_actions()[0, agent_id].astype(int).tolist()

    def get_total_actions(self) -> int:
        return self.n_actions

    def get_visibility_matrix(self) -> np.ndarray:
        """[N, N + E] bool: which units (allies first) each living agent sees (SMAC's)."""
        b, N = self.vec.battle, self.n_agents
        _, _, dist = b.pairwise()
        sight = b.rosters.sight[b.rid[0]][:, None]
        vis = (dist[0, :N] < sight) & b.alive[0][None, :] & b.alive[0, :N, None]
        np.fill_diagonal(vis[:, :N], False)
        return vis

    def get_env_info(self) -> dict[str, Any]:
        info = super().get_env_info()
        info["agent_features"] = list(self.ally_state_attr_names)
        info["enemy_features"] = list(self.enemy_state_attr_names)
        return info

    def get_stats(self) -> dict[str, Any]:
        s = self.vec.get_stats()
        return {
            "battles_won": s["battles_won"],
            "battles_game": s["battles_game"],
            "battles_draw": s["timeouts"],
            "win_rate": s["win_rate"],
            "timeouts": s["timeouts"],
            "restarts": self.force_restarts,
        }

    # -- seeding, rendering, replays -------------------------------------------------------
    def seed(self, seed: int | None = None) -> int | None:
        """SMAC's `seed()` returns the seed; `seed(s)` also re-seeds from the next reset."""
        if seed is not None:
            self._seed = seed
            self.vec.seed(seed)
        return self._seed

    def render(self, mode: str = "human"):
        """Draw the battle now: mode "rgb_array" returns the image [H, W, 3] uint8; "human"
        shows it in a matplotlib window where one can open (skirmish has no game window)."""
        from actors.envs.skirmish.render import draw_frame, snapshot

        if mode not in ("human", "rgb_array"):
            raise EnvError(f"render mode must be 'human' or 'rgb_array', got {mode!r}")
        title = f"{self.map_name}  t={self._episode_steps}"
        frame = draw_frame(snapshot(self.vec), title)
        if mode == "rgb_array":
            return frame
        import matplotlib.pyplot as plt

        if not plt.isinteractive() and plt.get_backend().lower() == "agg":
            log.warning("render(mode='human'): no display here; use save_replay() for a GIF")
            return None
        if self._figure is None:
            self._figure = plt.figure()
        plt.figure(self._figure.number)
        plt.clf()
        plt.imshow(frame)
        plt.axis("off")
        plt.pause(0.001)
        return None

    def save_replay(self) -> str | None:
        """Write the episodes played since the last call (at most REPLAY_EPISODES) as one
        animated GIF `<replay_prefix or map_name>_<time>.gif` in `replay_dir` (default: the
        working directory), where SMAC saves an SC2 replay; returns its path."""
        from actors.envs.skirmish.render import FrameDrawer, write_images

        episodes = [e for e in self._replays if len(e["frames"]) > 1]
        if not episodes:
            log.warning("save_replay: no episode played yet, nothing written")
            return None
        frames = []
        for k, ep in enumerate(episodes):
            drawer = FrameDrawer({**ep["statics"], **ep["frames"][0]})
            for t, dyn in enumerate(ep["frames"]):
                title = f"{self.map_name}  episode {k + 1}/{len(episodes)}  t={t}"
                frames.append(drawer.draw({**ep["statics"], **dyn}, title))
            drawer.close()
        prefix = self.replay_prefix or Path(str(self.map_name)).stem
        stamp = time.strftime("%Y-%m-%d-%H-%M-%S")
        path = Path(self.replay_dir or ".") / f"{prefix}_{stamp}.gif"
        n = 1
        while path.exists():
            n += 1
            path = path.with_name(f"{prefix}_{stamp}_{n}.gif")
        write_images(frames, path)
        log.info("Replay saved at: %s", path)
        current = self._replays[-1] if not self.vec.done[0] else None
        self._replays.clear()
        if current is not None:  # the episode goes on: record the rest of it
            self._replays.append({"statics": current["statics"], "frames": current["frames"][-1:]})
        return str(path)

    def close(self) -> None:
        self.vec.close()
        if self._figure is not None:
            import matplotlib.pyplot as plt

            plt.close(self._figure)
            self._figure = None

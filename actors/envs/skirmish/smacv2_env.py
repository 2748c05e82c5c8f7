"""SMACv2's `StarCraftCapabilityEnvWrapper` (oxwhirl/smacv2) over skirmish.

For code written against SMACv2 (e.g. EPyMARL's `sc2v2` configs): `map_name` is SMACv2's
"10gen_protoss" / "10gen_terran" / "10gen_zerg" and `capability_config` its distributions,
which become a randomised skirmish map (`scenario.py`): `team_gen` with `dist_type:
weighted_teams` (unit_types, weights, exception_unit_types), `start_positions` with
`dist_type` surrounded_and_reflect (p), surrounded or reflect_position (map_x, map_y), and
`n_units` / `n_enemies`. SMACv2's keywords `obs_own_pos`, `use_unit_ranges` and
`min_attack_range` are honoured; `num_fov_actions` and `kill_unit_step_mul` do nothing
here (as in SMACv2 without conic_fov or health levels). The other options SMACv2 offers
raise an EnvError naming them: `conic_fov`, `fully_observable`, `obs_starcraft=False`,
`prob_obs_enemy` other than 1, `action_mask=False`, and the capability keys `attack`,
`health`, `enemy_mask`, `team_gen.observe: False`. Every SMAC keyword works as in
`StarCraft2Env`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from actors.envs.base import EnvError
from actors.envs.skirmish.smac_env import StarCraft2Env
from actors.envs.skirmish.spec import MapSpec, parse_map

RACES = {
    "10gen_protoss": ["stalker", "zealot", "colossus"],
    "10gen_terran": ["marine", "marauder", "medivac"],
    "10gen_zerg": ["zergling", "hydralisk", "baneling"],
}
START_MODES = {
    "surrounded_and_reflect": "surrounded_and_reflect",
    "surrounded": "surrounded",
    "reflect_position": "reflect",
}
# SMACv2's keywords beyond SMAC's, with its defaults.
V2_KEYWORDS = {
    "obs_own_pos": False, "obs_starcraft": True, "conic_fov": False, "num_fov_actions": 12,
    "use_unit_ranges": False, "min_attack_range": 2, "kill_unit_step_mul": 2,
    "fully_observable": False, "capability_config": None, "prob_obs_enemy": 1.0,
    "action_mask": True,
}  # fmt: skip
# Values skirmish can honour for SMACv2's options that it does not model.
ONLY = {"obs_starcraft": True, "conic_fov": False, "fully_observable": False,
        "prob_obs_enemy": 1.0, "action_mask": True}  # fmt: skip
EPISODE_LIMIT = 200  # SMACv2's limit on its 10gen maps


def _team_gen(tg: Any) -> dict:
    if not isinstance(tg, dict) or tg.get("dist_type") != "weighted_teams":
        raise EnvError("capability_config.team_gen: only dist_type 'weighted_teams' is "
                       f"supported, got {tg!r}")  # fmt: skip
    if not tg.get("observe", True):
        raise EnvError("capability_config.team_gen.observe=False (zero-padded unit types) is "
                       "not supported")  # fmt: skip
    out = {"unit_types": list(tg.get("unit_types", [])), "weights": list(tg.get("weights", []))}
    if "exception_unit_types" in tg:
        out["exception_unit_types"] = list(tg["exception_unit_types"])
    return out


def capability_map(map_name: str, cfg: Any, own_pos: bool, unit_ranges: bool,
                   min_attack_range: float) -> MapSpec:  # fmt: skip
    """The randomised skirmish map of SMACv2's `map_name` and `capability_config`."""
    if map_name not in RACES:
        raise EnvError(f"map_name must be one of SMACv2's {sorted(RACES)}, got {map_name!r}")
    if not isinstance(cfg, dict) or "n_units" not in cfg:
        raise EnvError(f"capability_config must be a mapping with n_units, got {cfg!r}")
    for key in cfg:
        if key not in ("n_units", "n_enemies", "team_gen", "start_positions"):
            raise EnvError(f"capability_config.{key} is not supported; supported: n_units, "
                           "n_enemies, team_gen, start_positions")  # fmt: skip
    race = RACES[map_name]
    raw: dict[str, Any] = {
        "episode_limit": EPISODE_LIMIT, "obs_own_pos": bool(own_pos),
        "unit_ranges": bool(unit_ranges), "min_attack_range": float(min_attack_range),
        "type_order": {"allies": race, "enemies": race}, "unit_type_bits": 3,
        "n_units": cfg["n_units"], "n_enemies": cfg.get("n_enemies", cfg["n_units"]),
    }  # fmt: skip
    tg = cfg.get("team_gen", {"dist_type": "weighted_teams", "unit_types": race[:1],
                              "weights": [1.0]})  # fmt: skip
    raw["team_gen"] = _team_gen(tg)
    sp = cfg.get("start_positions")
    if sp is not None:
        mode = START_MODES.get(sp.get("dist_type")) if isinstance(sp, dict) else None
        if mode is None:
            raise EnvError("capability_config.start_positions.dist_type must be one of "
                           f"{sorted(START_MODES)}, got {sp!r}")  # fmt: skip
        raw["start_positions"] = {"mode": mode, "p": float(sp.get("p", 0.5))}
        raw["map_size"] = [sp.get("map_x", 32), sp.get("map_y", 32)]
    return parse_map(map_name, raw, "capability_config")


class StarCraftCapabilityEnvWrapper(StarCraft2Env):
    """SMACv2's wrapper: SMAC's keywords plus SMACv2's (module docstring); a map drawn per
    episode from `capability_config`. Adds `get_capabilities` and `cap_shape`."""

    def __init__(self, **kwargs: Any):
        v2 = {k: kwargs.pop(k, d) for k, d in V2_KEYWORDS.items()}
        for key, ok in ONLY.items():
            if v2[key] != ok:
                raise EnvError(f"{key}={v2[key]!r} is not supported by skirmish; use {ok!r}")
        spec = capability_map(kwargs.pop("map_name", "10gen_protoss"), v2["capability_config"],
                              v2["obs_own_pos"], v2["use_unit_ranges"],
                              v2["min_attack_range"])  # fmt: skip
        super().__init__(map_name=spec, **kwargs)
        self.capability_config = v2["capability_config"]
        self.obs_own_pos, self.use_unit_ranges = v2["obs_own_pos"], v2["use_unit_ranges"]
        self.min_attack_range = v2["min_attack_range"]

    def get_cap_size(self) -> int:
        """SMACv2's capability size: the type one-hot."""
        return self.unit_type_bits

    def get_capabilities_agent(self, agent_id: int) -> np.ndarray:
        return self.vec.battle.roster(0).onehot[agent_id].astype(np.float32)

    def get_capabilities(self) -> np.ndarray:
        """Every agent's type one-hot, concatenated [n_agents * cap_shape] (SMACv2's)."""
        return self.vec.battle.roster(0).onehot[: self.n_agents].astype(np.float32).ravel()

    def get_env_info(self) -> dict[str, Any]:
        info = super().get_env_info()
        info["cap_shape"] = self.get_cap_size()
        return info

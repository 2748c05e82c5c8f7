"""`SkirmishConfig`: the simulator's options and SMAC's tensor and reward keywords."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from actors.envs.base import EnvError


@dataclass(frozen=True)
class SkirmishConfig:
    """Options of a skirmish env (SMAC's constructor defaults).

    The SMAC keywords here change the tensors and rewards exactly as they do in oxwhirl
    SMAC's `StarCraft2Env` (see `variants.py` for the observation and state layouts);
    with their defaults the tensors are SMAC's default ones.

    Attributes:
        move_amount: distance of a move order (SMAC: 2).
        step_mul: game loops per agent step (SMAC: 8).
        substeps: physics sub-steps per agent step (accuracy vs speed).
        sight_range / shoot_range: SMAC's fixed 9 and 6 (maps with `unit_ranges` use each
            unit's own instead).
        reward_death_value / reward_win / reward_defeat: SMAC's 10 / 200 / 0.
        reward_scale / reward_scale_rate: scale so a perfect episode returns 20.
        reward_only_positive: SMAC's default; the reward is |damage + kill bonus|.
        reward_negative_scale: without reward_only_positive, damage taken and allied deaths
            cost this times their value (SMAC: 0.5).
        reward_sparse: SMAC's sparse reward: 0 per step, +1 on a win, -1 on a defeat (then
            divided by max_reward / reward_scale_rate when reward_scale, as SMAC does).
        obs_all_health: observations hold every visible unit's health and shield (SMAC).
        obs_own_health: an agent observes its own health and shield (implied by
            obs_all_health, as in SMAC).
        obs_last_action: each visible ally's block ends with its last action one-hot.
        obs_timestep_number: observations end with episode step / episode_limit.
        obs_instead_of_state: the state is all agents' observations concatenated.
        state_last_action: append all agents' last actions to the state.
        state_timestep_number: the state ends with episode step / episode_limit.
        start_jitter: uniform shift (cells) of each side's whole formation at reset (fixed
            maps; randomised maps draw their positions instead).
        unit_jitter: uniform per-unit start noise (cells) within the formation.
        shield_regen_delay_s / shield_regen_per_s: protoss shields regenerate after no damage.
        acquire_range: how far (edge to edge) a scripted enemy on attack-move looks for an
            agent to attack; farther agents are ignored until it reaches the agents' spawn.
        bane_dodge: a scripted enemy ground unit that comes within a living agent baneling's
            burst radius plus this margin backs away from it (SC2's AI avoids baneling
            splash; see README.md, "Enemy splash avoidance"); negative: no avoidance. 0.3:
            the value that meets results/skirmish/README.md's rule on most bane maps.
    """

    move_amount: float = 2.0
    step_mul: int = 8
    substeps: int = 2
    sight_range: float = 9.0
    shoot_range: float = 6.0
    reward_death_value: float = 10.0
    reward_win: float = 200.0
    reward_defeat: float = 0.0
    reward_scale: bool = True
    reward_scale_rate: float = 20.0
    reward_only_positive: bool = True
    reward_negative_scale: float = 0.5
    reward_sparse: bool = False
    obs_all_health: bool = True
    obs_own_health: bool = True
    obs_last_action: bool = False
    obs_timestep_number: bool = False
    obs_instead_of_state: bool = False
    state_last_action: bool = True
    state_timestep_number: bool = False
    start_jitter: float = 1.0
    unit_jitter: float = 0.05
    shield_regen_delay_s: float = 10.0
    shield_regen_per_s: float = 2.0
    acquire_range: float = 9.0
    bane_dodge: float = 0.3

    def validate(self) -> None:
        if self.step_mul < 1 or self.substeps < 1 or self.step_mul % self.substeps:
            raise EnvError("step_mul and substeps must be >= 1 with substeps dividing step_mul")
        if not (0 < self.shoot_range <= self.sight_range):
            raise EnvError("need 0 < shoot_range <= sight_range")
        if (
            self.move_amount <= 0
            or self.reward_scale_rate <= 0
            or min(self.start_jitter, self.unit_jitter) < 0
        ):
            raise EnvError("move_amount and reward_scale_rate must be > 0, start_jitter >= 0")
        if self.acquire_range < 0:
            raise EnvError("acquire_range must be >= 0")
        if not math.isfinite(self.reward_win) or self.reward_defeat > 0:
            raise EnvError("reward_win must be finite and reward_defeat <= 0")
        if not (math.isfinite(self.reward_negative_scale) and self.reward_negative_scale >= 0):
            raise EnvError(f"reward_negative_scale must be >= 0, got {self.reward_negative_scale}")

    @property
    def own_health(self) -> bool:
        """Whether agents observe their own health (SMAC: obs_all_health implies it)."""
        return self.obs_all_health or self.obs_own_health


def make_config(**overrides: Any) -> SkirmishConfig:
    """SkirmishConfig with keyword overrides; unknown keys raise EnvError listing valid ones."""
    valid = [f.name for f in fields(SkirmishConfig)]
    unknown = sorted(set(overrides) - set(valid))
    if unknown:
        raise EnvError(f"unknown skirmish options {unknown}; valid options: {valid}")
    defaults = SkirmishConfig()
    kinds = {bool: (bool, np.bool_), int: numbers.Integral, float: numbers.Real}
    for key, value in overrides.items():
        want = type(getattr(defaults, key))
        is_bool = isinstance(value, bool | np.bool_)
        if not isinstance(value, kinds.get(want, want)) or (want is not bool and is_bool):
            raise EnvError(f"skirmish option {key}: expected {want.__name__}, got {value!r}")
    cfg = SkirmishConfig(**overrides)
    cfg.validate()
    return cfg

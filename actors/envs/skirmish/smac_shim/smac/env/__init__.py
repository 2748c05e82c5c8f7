"""`smac.env` on skirmish: `StarCraft2Env` (SMAC's keywords) and `MultiAgentEnv`."""

from actors.envs.skirmish.smac_env import MultiAgentEnv, StarCraft2Env

__all__ = ["MultiAgentEnv", "StarCraft2Env"]

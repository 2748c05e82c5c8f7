"""`smac.env` on skirmish: `StarCraft2Env` (SMAC's keywords) and `MultiAgentEnv`."""

from actors.envs.skirmish.multiagentenv import MultiAgentEnv
from actors.envs.skirmish.smac_env import StarCraft2Env

__all__ = ["MultiAgentEnv", "StarCraft2Env"]

"""`smacv2.env` on skirmish (SMACv2's capability wrapper over skirmish's StarCraft2Env)."""

from actors.envs.skirmish.multiagentenv import MultiAgentEnv
from actors.envs.skirmish.smacv2_env import StarCraftCapabilityEnvWrapper

__all__ = ["MultiAgentEnv", "StarCraftCapabilityEnvWrapper"]

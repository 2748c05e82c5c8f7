"""`smacv2.env.starcraft2.wrapper` on skirmish (what EPyMARL's smacv2_wrapper imports)."""

from actors.envs.skirmish.smacv2_env import StarCraftCapabilityEnvWrapper

__all__ = ["StarCraftCapabilityEnvWrapper"]

"""`smac.env.multiagentenv` on skirmish (PyMARL2's vendored env imports its base class)."""

from actors.envs.skirmish.multiagentenv import MultiAgentEnv

__all__ = ["MultiAgentEnv"]

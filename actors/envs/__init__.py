"""Environments with SMAC's API; see `actors.envs.base` for the interfaces."""

from actors.envs.base import EnvError, EnvInfo, MultiAgentEnv, VecEnv
from actors.envs.registry import env_ids, env_info, get_spec, make_env, make_vec_env

__all__ = [
    "EnvError",
    "EnvInfo",
    "MultiAgentEnv",
    "VecEnv",
    "env_ids",
    "env_info",
    "get_spec",
    "make_env",
    "make_vec_env",
]

"""skirmish: the built-in SMAC-compatible StarCraft micromanagement simulator.

Ids `skirmish/<map>` for the built-in maps and `skirmish/custom` (argument `map_file=PATH`,
a YAML map, see README.md). `SkirmishEnv` is SMAC's single-env API; `SkirmishVecEnv`
steps many battles per NumPy call; `StarCraft2Env` takes oxwhirl SMAC's constructor
keywords (the PyMARL-family drop-in, README.md "PyMARL, EPyMARL, PyMARL2").
"""

from __future__ import annotations

from importlib import resources
from typing import Any

from actors.envs.skirmish.config import SkirmishConfig, make_config
from actors.envs.skirmish.env import SkirmishEnv, SkirmishVecEnv
from actors.envs.skirmish.maps import builtin_map, builtin_map_names, load_map_file
from actors.envs.skirmish.multiagentenv import MultiAgentEnv
from actors.envs.skirmish.smac_env import StarCraft2Env
from actors.envs.skirmish.spec import MapSpec

__all__ = [
    "MapSpec",
    "MultiAgentEnv",
    "SkirmishConfig",
    "SkirmishEnv",
    "SkirmishVecEnv",
    "StarCraft2Env",
    "builtin_map",
    "builtin_map_names",
    "example_map_file",
    "load_map_file",
    "make_skirmish",
    "make_skirmish_vec",
    "smac_shim_path",
]


def example_map_file() -> str:
    """Path of the packaged example custom map (the default of `skirmish/custom`)."""
    return str(resources.files("actors.envs.skirmish").joinpath("data/custom_example.yaml"))


def smac_shim_path() -> str:
    """A folder holding a `smac` package (`smac.env.StarCraft2Env` = skirmish's): put it
    first on PYTHONPATH to run unmodified PyMARL-family code on skirmish (README.md)."""
    return str(resources.files("actors.envs.skirmish").joinpath("smac_shim"))


def _spec(map_name: str | None, map_file: str | None) -> MapSpec:
    if map_file is not None:
        return load_map_file(map_file)
    if map_name is None:
        return load_map_file(example_map_file())
    return builtin_map(map_name)


def make_skirmish(
    seed: int | None = None,
    map_name: str | None = None,
    map_file: str | None = None,
    **options: Any,
) -> SkirmishEnv:
    """One skirmish env. Args: a built-in `map_name` or a YAML `map_file`; `options` are
    `SkirmishConfig` fields (unknown ones raise EnvError listing the valid ones)."""
    return SkirmishEnv(_spec(map_name, map_file), seed=seed, config=make_config(**options))


def make_skirmish_vec(
    num_envs: int,
    seed: int | None = None,
    map_name: str | None = None,
    map_file: str | None = None,
    **options: Any,
) -> SkirmishVecEnv:
    """`num_envs` battles stepped together; env k is seeded `seed + k`."""
    spec = _spec(map_name, map_file)
    return SkirmishVecEnv(spec, num_envs, seed=seed, config=make_config(**options))

"""The one explicit env registry: id -> how to build the env (single and batched).

Ids are "<family>/<name>" (`matrix/two_step`, later `skirmish/3m`, `smac/3m`). Nothing
registers itself on import: every family is listed in `_families()` below. Two kinds of id are
built on request instead of listed: `skirmish/bane_z<N>`, bane_vs_bane with N allied
zerglings (the dissertation's redundancy variants with any N), and the path of a skirmish map
file a user wrote (`path/to/map.yaml`, any id ending in .yaml or .yml), which trains like a
built-in map of the skirmish family.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from actors.envs.base import EnvError, EnvInfo, MultiAgentEnv, SerialVecEnv, VecEnv, env_info_of
from actors.envs.matrix import make_four_game, make_two_step
from actors.envs.skirmish import (
    builtin_map,
    builtin_map_names,
    load_map_file,
    make_skirmish,
    make_skirmish_vec,
)
from actors.envs.skirmish.maps import BANE_VARIANT
from actors.envs.smac_backend import SMAC_MAPS, make_smac_factory

MAP_FILE_SUFFIXES = (".yaml", ".yml")  # an env id ending so is the path of a skirmish map file


@dataclass(frozen=True)
class EnvSpec:
    """How to build one registered env.

    Attributes:
        id: "<family>/<name>".
        make: factory `(seed=..., **args) -> MultiAgentEnv`.
        make_vec: optional native batched factory `(num_envs, seed=..., **args) -> VecEnv`;
            without one, `make_vec_env` steps `num_envs` single envs serially.
        description: one line for `credit env list`.
    """

    id: str
    make: Callable[..., MultiAgentEnv]
    make_vec: Callable[..., VecEnv] | None = None
    description: str = ""


def _families() -> list[EnvSpec]:
    specs = [
        EnvSpec("matrix/two_step", make_two_step, description="QMIX two-step game (optimum 8)"),
        EnvSpec(
            "matrix/four_game", make_four_game, description="seed Fig. 5.1 four-game (optimum 8)"
        ),
    ]
    specs += _skirmish_specs()
    specs += [
        EnvSpec(f"smac/{m}", make_smac_factory(m), description=f"StarCraft II SMAC {m} (needs SC2)")
        for m in SMAC_MAPS
    ]
    return specs


def _fixed_map_spec(env_id: str, where: dict[str, str], description: str) -> EnvSpec:
    """An env of one skirmish map; `where` is make_skirmish's `map_name` or `map_file`, which
    env arguments cannot change (skirmish/custom is the env that takes `map_file`)."""

    def options_of(options: dict[str, Any]) -> dict[str, Any]:
        taken = sorted({"map_file", "map_name"} & set(options))
        if taken:
            raise EnvError(
                f"env {env_id!r} is one fixed map: drop the env argument(s) {taken} "
                "(skirmish/custom takes map_file; or give the map file as the env)"
            )
        return options

    def make(seed: int | None = None, **options: Any) -> MultiAgentEnv:
        return make_skirmish(seed, **where, **options_of(options))

    def make_vec(num_envs: int, seed: int | None = None, **options: Any) -> VecEnv:
        return make_skirmish_vec(num_envs, seed, **where, **options_of(options))

    return EnvSpec(env_id, make, make_vec, description)


def _skirmish_map_spec(name: str) -> EnvSpec:
    """`skirmish/<name>` for a built-in map (or a generated `bane_z<N>`)."""
    kind = "SMACv2-style randomised scenario" if builtin_map(name).randomised else "SMAC map"
    return _fixed_map_spec(
        f"skirmish/{name}", {"map_name": name}, f"skirmish simulator, {kind} {name}"
    )


def _skirmish_specs() -> list[EnvSpec]:
    """`skirmish/<map>` for each built-in map, and `skirmish/custom` (arg `map_file=PATH`)."""

    def make_custom(seed: int | None = None, map_file: str | None = None, **options: Any):
        return make_skirmish(seed, map_file=map_file, **options)

    def make_custom_vec(
        num_envs: int, seed: int | None = None, map_file: str | None = None, **options: Any
    ):
        return make_skirmish_vec(num_envs, seed, map_file=map_file, **options)

    custom = EnvSpec(
        "skirmish/custom",
        make_custom,
        make_custom_vec,
        "skirmish map from a YAML file (map_file=PATH)",
    )
    return [_skirmish_map_spec(n) for n in builtin_map_names()] + [custom]


def is_map_file(env_id: str) -> bool:
    """Whether `env_id` is the path of a skirmish map file rather than a registered id."""
    return env_id.endswith(MAP_FILE_SUFFIXES)


def env_family(env_id: str) -> str:
    """The family of an env id ("skirmish" for a map file): it picks the config layers."""
    return "skirmish" if is_map_file(env_id) else env_id.partition("/")[0]


def env_name(env_id: str) -> str:
    """A short name of the env for file names and titles: the map file's stem, else the id
    after its family (`skirmish/3m` -> "3m")."""
    if is_map_file(env_id):
        return Path(env_id).stem
    return env_id.partition("/")[2] or env_id


def _map_file_spec(path: str) -> EnvSpec:
    """A map file as an env: read (and checked) here, so that a bad file fails before any
    training with an EnvError naming the file and the field."""
    try:
        name = load_map_file(path).name
    except (OSError, UnicodeDecodeError) as e:
        raise EnvError(f"map file {path!r} cannot be read: {e}") from None
    return _fixed_map_spec(path, {"map_file": path}, f"skirmish map file {path} (map {name})")


REGISTRY: dict[str, EnvSpec] = {spec.id: spec for spec in _families()}


def env_ids() -> list[str]:
    return sorted(REGISTRY)


def get_spec(env_id: str) -> EnvSpec:
    """Return the spec of `env_id`; unknown ids raise EnvError listing the valid ones."""
    if env_id in REGISTRY:
        return REGISTRY[env_id]
    if is_map_file(env_id):
        return _map_file_spec(env_id)
    family, _, name = env_id.partition("/")
    if family == "skirmish" and BANE_VARIANT.fullmatch(name):
        return _skirmish_map_spec(name)  # generated on the fly (errors name the valid N)
    raise EnvError(
        f"unknown env {env_id!r}; valid envs: {', '.join(env_ids())}, "
        "skirmish/bane_z<N> (bane_vs_bane with N allied zerglings), or the path of a "
        "skirmish map file (ending in .yaml or .yml)"
    )


def _call(factory: Callable[..., Any], env_id: str, *args: Any, **kwargs: Any) -> Any:
    params = inspect.signature(factory).parameters
    if not any(p.kind is p.VAR_KEYWORD for p in params.values()):
        for key in kwargs:
            if key not in params:
                valid = [k for k in params if k not in ("seed", "num_envs")]
                raise EnvError(f"env {env_id!r} has no argument {key!r}; valid arguments: {valid}")
    return factory(*args, **kwargs)


def make_env(env_id: str, seed: int | None = None, **args: Any) -> MultiAgentEnv:
    """Build one SMAC-API env. Unknown ids and arguments raise EnvError naming them."""
    spec = get_spec(env_id)
    return _call(spec.make, env_id, seed=seed, **args)


def make_vec_env(env_id: str, num_envs: int, seed: int | None = None, **args: Any) -> VecEnv:
    """Build `num_envs` envs stepped together; env k is seeded with `seed + k`."""
    if num_envs < 1:
        raise EnvError(f"num_envs must be >= 1, got {num_envs}")
    spec = get_spec(env_id)
    if spec.make_vec is not None:
        return _call(spec.make_vec, env_id, num_envs, seed=seed, **args)
    envs = [
        _call(spec.make, env_id, seed=None if seed is None else seed + k, **args)
        for k in range(num_envs)
    ]
    return SerialVecEnv(envs)


def env_info(env_id: str, **args: Any) -> EnvInfo:
    env = make_env(env_id, seed=0, **args)
    try:
        return env_info_of(env)
    finally:
        env.close()

"""Where a run's shipped YAML layers are: the `layers/` folder of the installed
`cluster.config` package (package data, found through importlib.resources), the layers
that apply to an (algorithm, env) pair, and the recipes put on top of them."""

from __future__ import annotations

from importlib import resources
from importlib.resources.abc import Traversable

from actors.envs.registry import env_family, is_map_file
from cluster.config.schema import ConfigError
from learner.registry import get_algo

CONFIG_PACKAGE = "cluster.config"  # the shipped layers are package data: cluster/config/layers/
SHIPPED_RECIPE = "shipped"
# Older names of recipes, read as the name they have now (so old configs and commands work).
RECIPE_ALIASES = {"seed": "dissertation"}


def recipe_name(recipe: object) -> str:
    """The current name of `recipe` (an alias in RECIPE_ALIASES gives the name it stands for)."""
    return RECIPE_ALIASES.get(str(recipe), str(recipe))


def config_root() -> Traversable:
    """The shipped `layers/` folder of the installed `cluster.config` package.

    Raises:
        ConfigError: the folder is not there (an install that left the package data out).
    """
    root = resources.files(CONFIG_PACKAGE) / "layers"
    if not root.is_dir():
        raise ConfigError(
            f"the shipped configs are missing: {root} does not exist in the installed "
            f"{CONFIG_PACKAGE!r} package; reinstall credit (`pip install .` copies "
            "cluster/config/layers/ as package data)"
        )
    return root


def default_files(algo: str, env_id: str) -> list[Traversable]:
    """The shipped YAML layers for (algo, env), later ones winning.

    Required (a missing one is a ConfigError naming it): envs/<family>.yaml (the env
    family's schedule, evaluation and value-family data flow) and algos/<algo>.yaml (the
    algorithm's own hyper-parameters, including data flow it fixes, e.g. the policy-gradient
    family's 4 new episodes per step and 32-episode cycling buffer). Optional, used when
    present: envs/<family>.<algo family>.yaml (what one algorithm family needs on that env
    family, e.g. the value family's measured settings on SMAC-like maps),
    envs/<family>.<algo>.yaml (what one algorithm needs on that env family, e.g. RDN's critic
    targets on SMAC-like maps) and envs/<family>/<name>.yaml (what one built-in map needs;
    a user's map file, of the skirmish family, has no layer of its own).
    """
    family, name = env_family(env_id), env_id.partition("/")[2]
    algo_family = get_algo(algo).family
    root = config_root()
    required = [root / "envs" / f"{family}.yaml", root / "algos" / f"{algo}.yaml"]
    for layer in required:
        if not layer.is_file():
            raise ConfigError(
                f"shipped config layer {layer} is missing: every env family needs "
                f"envs/<family>.yaml and every algorithm algos/<algo>.yaml under {root}"
            )
    optional = [
        root / "envs" / f"{family}.{algo_family}.yaml",
        root / "envs" / f"{family}.{algo}.yaml",
    ]
    if not is_map_file(env_id):  # a user's map file has no layer of its own
        optional.append(root / "envs" / family / f"{name}.yaml")
    return required + [p for p in optional if p.is_file()]


def recipe_file(algo: str, recipe: str) -> Traversable | None:
    """The layer `recipes/<algo>.<recipe>.yaml` that `recipe` puts on top of the shipped layers
    (None for the shipped recipe itself).

    Raises:
        ConfigError: no such recipe for this algorithm; the message lists the valid ones.
    """
    if recipe == SHIPPED_RECIPE:
        return None
    folder = config_root() / "recipes"
    layer = folder / f"{algo}.{recipe}.yaml"
    if layer.is_file():
        return layer
    known = sorted(
        p.name[len(algo) + 1 : -len(".yaml")]
        for p in (folder.iterdir() if folder.is_dir() else [])
        if p.name.startswith(f"{algo}.") and p.name.endswith(".yaml")
    )
    aliases = [f"{old} (= {new})" for old, new in RECIPE_ALIASES.items() if new in known]
    raise ConfigError(
        f"recipe {recipe!r} is not a recipe of {algo}; valid recipes: "
        + ", ".join([SHIPPED_RECIPE, *known, *aliases])
    )

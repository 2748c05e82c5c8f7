"""The map catalogue: the built-in maps (`data/maps.yaml`), the generated bane variants
`bane_z<N>` of the dissertation's redundancy experiment, and custom map files; each parsed into a
`spec.MapSpec`."""

from __future__ import annotations

import re
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from actors.envs.base import EnvError
from actors.envs.skirmish.spec import MapSpec, parse_map, unit_types


@lru_cache(maxsize=1)
def _builtin_raw() -> dict[str, Any]:
    text = resources.files("actors.envs.skirmish").joinpath("data/maps.yaml").read_text()
    return yaml.safe_load(text)


def builtin_map_names() -> list[str]:
    return list(_builtin_raw())


BANE_VARIANT = re.compile(r"bane_z(\d+)")
BANE_VARIANT_MAX = 64  # allied zerglings of a generated bane variant (8 columns of 8)


def builtin_map(name: str) -> MapSpec:
    """A built-in map by name, or a generated bane variant `bane_z<N>` (`bane_variant`);
    unknown names raise EnvError listing the valid ones."""
    raw = _builtin_raw()
    if name not in raw:
        match = BANE_VARIANT.fullmatch(name)
        if match:
            return bane_variant(int(match.group(1)))
        raise EnvError(
            f"unknown skirmish map {name!r}; valid maps: {', '.join(raw)}, "
            f"or bane_z<N> (N allied zerglings, 0..{BANE_VARIANT_MAX})"
        )
    return parse_map(name, raw[name], "actors/envs/skirmish/data/maps.yaml")


def bane_variant(zerglings: int) -> MapSpec:
    """bane_vs_bane with `zerglings` allied zerglings (the dissertation's redundancy variants, any
    number, built without a file): the enemy keeps 20 zerglings and 4 banelings, the agents
    keep their 4 banelings at bane_vs_bane's baneling point, and the zerglings stand in
    bane_vs_bane's lines abreast (columns of 8) in front of them. Past three columns (24
    zerglings) the front line moves 0.9 cells (one column) towards the enemy per column, so
    the rear column stays where bane_vs_bane's is. bane_z20 is bane_vs_bane, bane_z15
    bane_med, bane_z10 bane_small; bane_z0 keeps the banelings at their point, 3 cells
    behind where bane_no_z puts them."""
    if not 0 <= zerglings <= BANE_VARIANT_MAX:
        raise EnvError(f"bane_z<N>: N must be in 0..{BANE_VARIANT_MAX}, got {zerglings}")
    raw = dict(_builtin_raw()["bane_vs_bane"])
    banes, lings = None, None
    for g in raw["allies"]:
        if g["type"] == "baneling":
            banes = dict(g)
        else:
            lings = dict(g)
    allies = [banes]
    if zerglings:
        gap = 2 * unit_types()["zergling"].radius + 0.15  # `_line`'s spacing
        columns = -(-zerglings // 8)
        x, y = lings["at"]
        shift = 0 if raw.get("formation") == "blob" else max(0, columns - 3) * gap
        lings.update(count=zerglings, at=[x + shift, y])
        allies.insert(0, lings)
    raw["allies"] = allies
    return parse_map(f"bane_z{zerglings}", raw, f"generated map bane_z{zerglings}")


def load_map_file(path: str | Path) -> MapSpec:
    """Read a custom map from a YAML file (schema: MAP_FIELDS, GROUP_FIELDS, plus `name`)."""
    p = Path(path)
    if not p.is_file():
        raise EnvError(f"map file {str(p)!r} does not exist")
    try:
        raw = yaml.safe_load(p.read_text())
    except yaml.YAMLError as e:
        raise EnvError(f"{p}: not valid YAML: {e}") from None
    if not isinstance(raw, dict):
        raise EnvError(f"{p}: a map file must hold a mapping")
    raw = dict(raw)
    name = raw.pop("name", p.stem)
    return parse_map(str(name), raw, str(p))

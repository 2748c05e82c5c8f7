"""Unit types and map specifications (built-in and custom YAML files).

A map file holds one map; the built-in maps live in `data/maps.yaml` with the same schema,
keyed by name. Every field of a map (see `MAP_FIELDS`) is checked, and an error names the
field and the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from typing import Any

import numpy as np
import yaml

from actors.envs.base import EnvError
from actors.envs.skirmish.scenario import (
    StartPositions,
    TeamGen,
    parse_start_positions,
    parse_team_gen,
    place,
)

LOOPS_PER_SECOND = 22.4  # SC2 game loops per second at "faster" speed
KINDS = ("ranged", "melee", "baneling", "healer", "colossus")
MAP_FIELDS = {
    "episode_limit": "steps before the episode is cut (int > 0)",
    "allies": "list of unit groups controlled by the agents",
    "enemies": "list of unit groups controlled by the scripted AI",
    "map_size": "[width, height] of the playable area (default [32, 32])",
    "type_order": "{allies: [...], enemies: [...]}: unit-type one-hot order per side",
    "unit_type_bits": "length of the type one-hot (default: number of types if > 1, else 0)",
    "attack_point": "[x, y] the enemy attack-moves to (default: the agents' spawn centre)",
    "formation": "'line' (default): groups in lines abreast facing along x; 'blob': SC2's spawn",
    "team_gen": "unit types drawn per episode (SMACv2's weighted_teams; replaces allies/enemies)",
    "n_units": "number of agents of a team_gen map (int >= 1)",
    "n_enemies": "number of enemies of a team_gen map (default: n_units)",
    "start_positions": "start positions drawn per episode: {mode: surrounded | reflect | "
    "surrounded_and_reflect, p: P(reflect)}",
    "obs_own_pos": "agents observe their own [x, y] / map size (SMACv2's obs_own_pos)",
    "unit_ranges": "each unit's own sight and attack range (SMACv2's use_unit_ranges)",
    "min_attack_range": "with unit_ranges: the least shoot range of an agent (default 2)",
}
GROUP_FIELDS = {
    "type": "unit type name",
    "count": "number of units (int >= 0)",
    "at": "[x, y] spawn point (see the map's 'formation'); omitted with start_positions",
    "positions": "explicit [[x, y], ...], one per unit (instead of 'at')",
}


@dataclass(frozen=True)
class UnitType:
    """Static stats of one unit type (see data/units.yaml for units and meanings)."""

    name: str
    hp: float
    shield: float
    armor: float
    damage: float
    hits: int
    bonus: dict[str, float]
    cooldown_s: float
    range: float
    speed: float
    radius: float
    attributes: tuple[str, ...]
    kind: str
    smac_max_cooldown: float
    hits_air: bool = False
    energy_max: float = 0.0
    energy_start: float = 0.0
    energy_regen_s: float = 0.0
    heal_per_s: float = 0.0
    hp_per_energy: float = 1.0
    splash_radius: float = 0.0
    splash_half_length: float = 0.0
    splash_half_width: float = 0.0
    sight: float = 9.0

    def hit_vs(self, victim: UnitType) -> tuple[float, float]:
        """Damage of one attack to `victim`: (to health after armour, to shields)."""
        per_hit = self.damage + sum(v for k, v in self.bonus.items() if k in victim.attributes)
        if self.hits == 0:
            return 0.0, 0.0
        to_health = max(0.5, per_hit - victim.armor) * self.hits
        return to_health, per_hit * self.hits


@lru_cache(maxsize=1)
def unit_types() -> dict[str, UnitType]:
    """All unit types from the package data file."""
    text = resources.files("actors.envs.skirmish").joinpath("data/units.yaml").read_text()
    raw = yaml.safe_load(text)
    out = {}
    for name, d in raw.items():
        d = dict(d)
        d["attributes"] = tuple(d["attributes"])
        out[name] = UnitType(name=name, **d)
    return out


@dataclass(frozen=True)
class UnitGroup:
    type: str
    count: int
    positions: tuple[tuple[float, float], ...]


@dataclass(frozen=True)
class MapSpec:
    """A battle: both sides' units with start positions, map size and episode limit.

    Attributes:
        name: map name.
        episode_limit: agent steps before the episode is cut.
        allies / enemies: one `UnitGroup` per unit type block (empty with `team_gen`; no
            positions with `start_positions`).
        map_size: (width, height) of the playable area.
        ally_types / enemy_types: unit-type one-hot order of each side.
        unit_type_bits: length of the one-hot (0 when the map has a single type).
        attack_point: where the scripted enemy attack-moves to (None: the agents' centre).
        team_gen: unit types drawn per episode (scenario.TeamGen), or None.
        start_positions: start positions drawn per episode (scenario.StartPositions), or None.
        own_pos: agents observe their own position (SMACv2's obs_own_pos).
        unit_ranges: each unit's own sight and attack range (SMACv2's use_unit_ranges), the
            attack range at least `min_attack_range`.
    """

    name: str
    episode_limit: int
    allies: tuple[UnitGroup, ...]
    enemies: tuple[UnitGroup, ...]
    map_size: tuple[float, float]
    ally_types: tuple[str, ...]
    enemy_types: tuple[str, ...]
    unit_type_bits: int
    attack_point: tuple[float, float] | None = None
    team_gen: TeamGen | None = None
    start_positions: StartPositions | None = None
    own_pos: bool = False
    unit_ranges: bool = False
    min_attack_range: float = 2.0

    @property
    def randomised(self) -> bool:
        """Whether each episode draws its own units or positions."""
        return self.team_gen is not None or self.start_positions is not None

    @property
    def n_agents(self) -> int:
        if self.team_gen is not None:
            return self.team_gen.n_units
        return sum(g.count for g in self.allies)

    @property
    def n_enemies(self) -> int:
        if self.team_gen is not None:
            return self.team_gen.n_enemies
        return sum(g.count for g in self.enemies)

    def side_pool(self, side: str) -> tuple[str, ...]:
        """The unit types that can appear on `side` ("allies" or "enemies"), sorted."""
        if self.team_gen is not None:
            return tuple(sorted(self.team_gen.unit_types))
        groups = self.allies if side == "allies" else self.enemies
        return tuple(sorted({g.type for g in groups if g.count}))

    @property
    def pool(self) -> tuple[str, ...]:
        """Every unit type of the map, sorted (the rows of its type table)."""
        return tuple(sorted(set(self.side_pool("allies")) | set(self.side_pool("enemies"))))


def _line(at: tuple[float, float], count: int, radius: float, facing: float) -> list:
    """Line abreast: columns of up to 8 along y, further columns stacked away from the enemy."""
    gap = 2 * radius + 0.15
    per_col = min(count, 8)
    out = []
    for k in range(count):
        col, row = divmod(k, per_col)
        y = at[1] + (row - (per_col - 1) / 2) * gap
        out.append((at[0] - facing * col * gap, y))
    return out


def _check_group(g: Any, where: str, drawn: bool) -> tuple[str, int]:
    """Validate a group's fields, type and count; return (type, count)."""
    if not isinstance(g, dict):
        raise EnvError(
            f"{where}: a unit group must be a mapping with fields {sorted(GROUP_FIELDS)}"
        )
    for key in g:
        if key not in GROUP_FIELDS:
            raise EnvError(f"{where}: unknown field {key!r}; valid fields: {sorted(GROUP_FIELDS)}")
    types = unit_types()
    name = g.get("type")
    if name not in types:
        raise EnvError(f"{where}.type: unknown unit type {name!r}; valid: {sorted(types)}")
    count = g.get("count")
    if not isinstance(count, int) or isinstance(count, bool) or count < 0:
        raise EnvError(f"{where}.count: must be an int >= 0, got {count!r}")
    if drawn and ("at" in g or "positions" in g):
        raise EnvError(f"{where}: with start_positions, give neither 'at' nor 'positions'")
    if not drawn and ("at" in g) == ("positions" in g):
        raise EnvError(f"{where}: give exactly one of 'at' or 'positions'")
    return name, count


def _parse_side(groups: Any, src: str, side: str, blob: bool, drawn: bool, size) -> tuple:
    """One side's groups; 'blob' places each group's units as SC2 does (scenario.place)."""
    if not isinstance(groups, list) or not groups:
        raise EnvError(f"{src}: field {side!r} must be a non-empty list of unit groups")
    types, parsed, points = unit_types(), [], []
    facing = 1.0 if side == "allies" else -1.0
    for i, g in enumerate(groups):
        where = f"{src}: field '{side}[{i}]'"
        name, count = _check_group(g, where, drawn)
        t = types[name]
        if drawn:
            pos = []
        elif "at" in g:
            at = g["at"]
            if not (isinstance(at, list | tuple) and len(at) == 2):
                raise EnvError(f"{where}.at: must be [x, y], got {at!r}")
            xy = (float(at[0]), float(at[1]))
            pos = [xy] * count if blob else _line(xy, count, t.radius, facing)
        else:
            pos = g["positions"]
            ok = isinstance(pos, list) and all(
                isinstance(p, list | tuple) and len(p) == 2 for p in pos
            )
            if not ok or len(pos) != count:
                raise EnvError(f"{where}.positions: must be {count} [x, y] pairs, got {pos!r}")
        parsed.append((name, count, [(float(x), float(y)) for x, y in pos]))
        points += [(t.radius, "air" in t.attributes, blob and "at" in g)] * (0 if drawn else count)
    if sum(c for _, c, _ in parsed) == 0:
        raise EnvError(f"{src}: field {side!r} has no units")
    if blob and not drawn:
        flat = np.array([p for _, _, ps in parsed for p in ps], np.float64).reshape(-1, 2)
        radius, air, spread = (np.array(c) for c in zip(*points, strict=True))
        flat = place(flat, radius, air, size, fixed=~spread)
        k, out = 0, []
        for name, count, _ in parsed:
            out.append((name, count, [tuple(p) for p in flat[k : k + count].tolist()]))
            k += count
        parsed = out
    return tuple(UnitGroup(n, c, tuple(ps)) for n, c, ps in parsed)


def _type_order(raw: dict, sides: dict, pool: list[str], source: str) -> tuple[dict, int]:
    order = raw.get("type_order", {"allies": pool, "enemies": pool})
    if not isinstance(order, dict) or set(order) != {"allies", "enemies"}:
        raise EnvError(f"{source}: field 'type_order' must be {{allies: [...], enemies: [...]}}")
    for side in ("allies", "enemies"):
        missing = set(sides[side]) - set(order[side])
        if missing:
            raise EnvError(f"{source}: field 'type_order.{side}' lacks {sorted(missing)}")
    default_bits = len(pool) if len(pool) > 1 else 0
    bits = raw.get("unit_type_bits", default_bits)
    need = max(len(order["allies"]), len(order["enemies"])) if bits else 0
    if not isinstance(bits, int) or bits < need:
        raise EnvError(f"{source}: field 'unit_type_bits' must be an int >= {need}, got {bits!r}")
    return order, bits


def _point(raw: dict, w: float, h: float, source: str) -> tuple[float, float] | None:
    point = raw.get("attack_point")
    if point is not None:
        ok = isinstance(point, list | tuple) and len(point) == 2
        if not ok or not (0 <= point[0] < w and 0 <= point[1] < h):
            raise EnvError(
                f"{source}: field 'attack_point' must be [x, y] on the map, got {point!r}"
            )
        point = (float(point[0]), float(point[1]))
    return point


def _flags(raw: dict, source: str) -> dict:
    """SMACv2's observation options of a map."""
    out = {}
    for key, attr in (("obs_own_pos", "own_pos"), ("unit_ranges", "unit_ranges")):
        v = raw.get(key, False)
        if not isinstance(v, bool):
            raise EnvError(f"{source}: field {key!r} must be true or false, got {v!r}")
        out[attr] = v
    mar = raw.get("min_attack_range", 2.0)
    if not isinstance(mar, int | float) or isinstance(mar, bool) or mar < 0:
        raise EnvError(f"{source}: field 'min_attack_range' must be a number >= 0, got {mar!r}")
    out["min_attack_range"] = float(mar)
    return out


def _random_fields(raw: dict, source: str) -> tuple[TeamGen | None, StartPositions | None]:
    team_gen = None
    if "team_gen" in raw:
        for side in ("allies", "enemies"):
            if side in raw:
                raise EnvError(f"{source}: field {side!r}: team_gen draws the units; drop it")
        n = raw.get("n_units")
        team_gen = parse_team_gen(
            raw["team_gen"], n, raw.get("n_enemies", n), list(unit_types()), source
        )
    else:
        for key in ("n_units", "n_enemies"):
            if key in raw:
                raise EnvError(f"{source}: field {key!r} needs 'team_gen'")
    starts = raw.get("start_positions")
    if starts is not None:
        starts = parse_start_positions(starts, source)
    return team_gen, starts


def parse_map(name: str, raw: Any, source: str) -> MapSpec:
    """Validate one map mapping; errors name the field and `source` (the file)."""
    if not isinstance(raw, dict):
        raise EnvError(f"{source}: map {name!r} must be a mapping with fields {sorted(MAP_FIELDS)}")
    for key in raw:
        if key not in MAP_FIELDS:
            raise EnvError(f"{source}: unknown field {key!r}; valid fields: {sorted(MAP_FIELDS)}")
    limit = raw.get("episode_limit")
    if not isinstance(limit, int) or isinstance(limit, bool) or limit <= 0:
        raise EnvError(f"{source}: field 'episode_limit' must be an int > 0, got {limit!r}")
    size = raw.get("map_size", [32, 32])
    if not (isinstance(size, list | tuple) and len(size) == 2 and min(size) > 0):
        raise EnvError(f"{source}: field 'map_size' must be [width, height] > 0, got {size!r}")
    formation = raw.get("formation", "line")
    if formation not in ("line", "blob"):
        raise EnvError(f"{source}: field 'formation' must be 'line' or 'blob', got {formation!r}")
    team_gen, starts = _random_fields(raw, source)
    sides: dict[str, tuple] = {"allies": (), "enemies": ()}
    if team_gen is None:
        for side in ("allies", "enemies"):
            sides[side] = _parse_side(raw.get(side), source, side, formation == "blob",
                                      starts is not None, size)  # fmt: skip
        present = {s: [g.type for g in sides[s]] for s in sides}
        pool = sorted({t for ts in present.values() for t in ts})
    else:
        pool = list(team_gen.unit_types)
        present = {"allies": pool, "enemies": pool}
    order, bits = _type_order(raw, present, pool, source)
    w, h = float(size[0]), float(size[1])
    for side in ("allies", "enemies"):
        for g in sides[side]:
            for x, y in g.positions:
                if not (0 <= x < w and 0 <= y < h):
                    raise EnvError(f"{source}: field {side!r}: position ({x}, {y}) is off the map")
    return MapSpec(
        name=name,
        episode_limit=limit,
        allies=sides["allies"],
        enemies=sides["enemies"],
        map_size=(w, h),
        ally_types=tuple(order["allies"]),
        enemy_types=tuple(order["enemies"]),
        unit_type_bits=bits,
        attack_point=_point(raw, w, h, source),
        team_gen=team_gen,
        start_positions=starts,
        **_flags(raw, source),
    )


def ordered_units(spec: MapSpec, side: str) -> tuple[list[str], np.ndarray]:
    """Unit type names and start positions [n, 2] of one side in SMAC's unit order.

    SMAC sorts the agents by (unit type id, x, y); enemies come in the same type order.
    """
    groups = spec.allies if side == "allies" else spec.enemies
    order = spec.ally_types if side == "allies" else spec.enemy_types
    units = [(order.index(g.type), x, y, g.type) for g in groups for x, y in g.positions]
    units.sort(key=lambda u: (u[0], u[1], u[2]))
    names = [u[3] for u in units]
    pos = np.array([[u[1], u[2]] for u in units], np.float64).reshape(-1, 2)
    return names, pos

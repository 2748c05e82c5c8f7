"""Unit types, map specifications (built-in and custom YAML files) and the env config.

A map file holds one map; the built-in maps live in `data/maps.yaml` with the same schema,
keyed by name. Every field of a map (see `MAP_FIELDS`) is checked, and an error names the
field and the file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from actors.envs.base import EnvError

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
}
GROUP_FIELDS = {
    "type": "unit type name",
    "count": "number of units (int >= 0)",
    "at": "[x, y] spawn point (see the map's 'formation')",
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
        allies / enemies: one `UnitGroup` per unit type block.
        map_size: (width, height) of the playable area.
        ally_types / enemy_types: unit-type one-hot order of each side.
        unit_type_bits: length of the one-hot (0 when the map has a single type).
        attack_point: where the scripted enemy attack-moves to (None: the agents' centre).
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

    @property
    def n_agents(self) -> int:
        return sum(g.count for g in self.allies)

    @property
    def n_enemies(self) -> int:
        return sum(g.count for g in self.enemies)


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


def _ring_points(step: float = 0.05, max_r: float = 12.0) -> np.ndarray:
    """Candidate offsets [K, 2] ordered by distance from the origin (then by angle)."""
    pts = [(0.0, 0.0)]
    for k in range(1, int(max_r / step) + 1):
        r = k * step
        n = max(6, int(2 * math.pi * r / step))
        a = np.arange(n) * (2 * math.pi / n)
        pts += list(zip(r * np.cos(a), r * np.sin(a), strict=True))
    return np.array(pts)


_RING = _ring_points()


def _place(at: tuple[float, float], count: int, radius: float, air: bool, placed: list) -> list:
    """Spawn `count` units around `at` the way SC2 creates units at a point: each on the
    free spot closest to it (ground units do not overlap ground units already placed, air
    units not air ones). `placed` holds (x, y, radius, air) of the side so far; extended."""
    out = []
    for _ in range(count):
        cand = np.asarray(at) + _RING
        ok = np.ones(len(cand), bool)
        for x, y, r, a in placed:
            if a == air:
                ok &= np.hypot(cand[:, 0] - x, cand[:, 1] - y) >= r + radius + 0.02
        x, y = cand[int(np.argmax(ok))]
        placed.append((float(x), float(y), radius, air))
        out.append((float(x), float(y)))
    return out


def _parse_group(g: Any, where: str, facing: float, blob: bool, placed: list) -> UnitGroup:
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
    if ("at" in g) == ("positions" in g):
        raise EnvError(f"{where}: give exactly one of 'at' or 'positions'")
    if "at" in g:
        at = g["at"]
        if not (isinstance(at, list | tuple) and len(at) == 2):
            raise EnvError(f"{where}.at: must be [x, y], got {at!r}")
        t, xy = types[name], (float(at[0]), float(at[1]))
        if blob:
            pos = _place(xy, count, t.radius, "air" in t.attributes, placed)
        else:
            pos = _line(xy, count, t.radius, facing)
    else:
        pos = g["positions"]
        ok = isinstance(pos, list) and all(isinstance(p, list | tuple) and len(p) == 2 for p in pos)
        if not ok or len(pos) != count:
            raise EnvError(f"{where}.positions: must be {count} [x, y] pairs, got {pos!r}")
        t = types[name]
        placed += [(float(x), float(y), t.radius, "air" in t.attributes) for x, y in pos]
    return UnitGroup(name, count, tuple((float(x), float(y)) for x, y in pos))


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
    sides = {}
    formation = raw.get("formation", "line")
    if formation not in ("line", "blob"):
        raise EnvError(f"{source}: field 'formation' must be 'line' or 'blob', got {formation!r}")
    for side, facing in (("allies", 1.0), ("enemies", -1.0)):
        placed: list = []
        groups = raw.get(side)
        if not isinstance(groups, list) or not groups:
            raise EnvError(f"{source}: field {side!r} must be a non-empty list of unit groups")
        sides[side] = tuple(
            _parse_group(g, f"{source}: field '{side}[{i}]'", facing, formation == "blob", placed)
            for i, g in enumerate(groups)
        )
        if sum(g.count for g in sides[side]) == 0:
            raise EnvError(f"{source}: field {side!r} has no units")
    used = sorted({g.type for s in sides.values() for g in s})
    order = raw.get("type_order", {"allies": used, "enemies": used})
    if not isinstance(order, dict) or set(order) != {"allies", "enemies"}:
        raise EnvError(f"{source}: field 'type_order' must be {{allies: [...], enemies: [...]}}")
    for side in ("allies", "enemies"):
        missing = {g.type for g in sides[side]} - set(order[side])
        if missing:
            raise EnvError(f"{source}: field 'type_order.{side}' lacks {sorted(missing)}")
    default_bits = len(used) if len(used) > 1 else 0
    bits = raw.get("unit_type_bits", default_bits)
    need = max(len(order["allies"]), len(order["enemies"])) if bits else 0
    if not isinstance(bits, int) or bits < need:
        raise EnvError(f"{source}: field 'unit_type_bits' must be an int >= {need}, got {bits!r}")
    w, h = float(size[0]), float(size[1])
    point = raw.get("attack_point")
    if point is not None:
        ok = isinstance(point, list | tuple) and len(point) == 2
        if not ok or not (0 <= point[0] < w and 0 <= point[1] < h):
            raise EnvError(
                f"{source}: field 'attack_point' must be [x, y] on the map, got {point!r}"
            )
        point = (float(point[0]), float(point[1]))
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
        attack_point=point,
    )


@lru_cache(maxsize=1)
def _builtin_raw() -> dict[str, Any]:
    text = resources.files("actors.envs.skirmish").joinpath("data/maps.yaml").read_text()
    return yaml.safe_load(text)


def builtin_map_names() -> list[str]:
    return list(_builtin_raw())


def builtin_map(name: str) -> MapSpec:
    """A built-in map by name; unknown names raise EnvError listing the valid ones."""
    raw = _builtin_raw()
    if name not in raw:
        raise EnvError(f"unknown skirmish map {name!r}; valid maps: {', '.join(raw)}")
    return parse_map(name, raw[name], "actors/envs/skirmish/data/maps.yaml")


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


@dataclass(frozen=True)
class SkirmishConfig:
    """Options of a skirmish env (SMAC's constructor defaults).

    Attributes:
        move_amount: distance of a move order (SMAC: 2).
        step_mul: game loops per agent step (SMAC: 8).
        substeps: physics sub-steps per agent step (accuracy vs speed).
        sight_range / shoot_range: SMAC's fixed 9 and 6.
        reward_death_value / reward_win / reward_defeat: SMAC's 10 / 200 / 0.
        reward_scale / reward_scale_rate: scale so a perfect episode returns 20.
        reward_only_positive: SMAC's default; the reward is |damage + kill bonus|.
        state_last_action: append all agents' last actions to the state.
        start_jitter: uniform shift (cells) of each side's whole formation at reset.
        unit_jitter: uniform per-unit start noise (cells) within the formation.
        shield_regen_delay_s / shield_regen_per_s: protoss shields regenerate after no damage.
        acquire_range: how far (edge to edge) a scripted enemy on attack-move looks for an
            agent to attack; farther agents are ignored until it reaches the agents' spawn.
        bane_dodge: a scripted enemy ground unit that comes within a living agent baneling's
            burst radius plus this margin backs away from it (SC2's AI avoids baneling
            splash; see README.md, "Enemy AI"); negative: no avoidance.
    """

    move_amount: float = 2.0
    step_mul: int = 8
    substeps: int = 2
    sight_range: float = 9.0
    shoot_range: float = 6.0
    reward_death_value: float = 10.0
    reward_win: float = 200.0
    reward_defeat: float = 0.0
    reward_scale: bool = True
    reward_scale_rate: float = 20.0
    reward_only_positive: bool = True
    state_last_action: bool = True
    start_jitter: float = 1.0
    unit_jitter: float = 0.05
    shield_regen_delay_s: float = 10.0
    shield_regen_per_s: float = 2.0
    acquire_range: float = 9.0
    bane_dodge: float = 0.5

    def validate(self) -> None:
        if self.step_mul < 1 or self.substeps < 1 or self.step_mul % self.substeps:
            raise EnvError("step_mul and substeps must be >= 1 with substeps dividing step_mul")
        if not (0 < self.shoot_range <= self.sight_range):
            raise EnvError("need 0 < shoot_range <= sight_range")
        if (
            self.move_amount <= 0
            or self.reward_scale_rate <= 0
            or min(self.start_jitter, self.unit_jitter) < 0
        ):
            raise EnvError("move_amount and reward_scale_rate must be > 0, start_jitter >= 0")
        if self.acquire_range < 0:
            raise EnvError("acquire_range must be >= 0")
        if not math.isfinite(self.reward_win) or self.reward_defeat > 0:
            raise EnvError("reward_win must be finite and reward_defeat <= 0")


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


def make_config(**overrides: Any) -> SkirmishConfig:
    """SkirmishConfig with keyword overrides; unknown keys raise EnvError listing valid ones."""
    valid = [f.name for f in fields(SkirmishConfig)]
    unknown = sorted(set(overrides) - set(valid))
    if unknown:
        raise EnvError(f"unknown skirmish options {unknown}; valid options: {valid}")
    cfg = SkirmishConfig(**overrides)
    cfg.validate()
    return cfg

"""SMACv2-style randomised scenarios: unit types and start positions drawn per episode.

A map with `team_gen` draws each episode's teams from weighted unit types; a map with
`start_positions` draws where the units start. The rules are SMACv2's (oxwhirl/smacv2,
`distributions.py`), reimplemented here and driven by each battle's own generator so that
a seed replays the same episodes:

* team_gen (SMACv2's "weighted_teams"): the agents' n_units types are drawn i.i.d. with
  `weights`, redrawn while every one of them is an `exception_unit_types` type (no team of
  medivacs only); the enemy team is the same list, plus n_enemies - n_units more drawn the
  same way when the enemy has more units (or cut when it has fewer).
* start_positions "reflect": each agent at a uniform point of the left half (x < w/2 - 1),
  enemy i at the mirror image (w - x_i, y_i) of agent i; extra enemies uniform on the right.
  "surrounded": the agents at the map centre; the enemies split into 1-4 groups (a uniform
  number, multinomial sizes), each group on its own diagonal at a uniform fraction of the
  way from the corner to 2 cells (per axis) off the centre. "surrounded_and_reflect":
  reflect with probability `p`, else surrounded.
* Units created at one point spread out as SC2 does (`place`): each takes the free spot
  nearest its point, in creation order (agents first), without overlapping a unit of its
  own layer (ground or air) placed before it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit

from actors.envs.base import EnvError

START_MODES = ("surrounded", "reflect", "surrounded_and_reflect")
TEAM_GEN_FIELDS = {
    "unit_types": "list of unit type names to draw from",
    "weights": "probability of each unit type (same length, sums to 1)",
    "exception_unit_types": "types that may not make up a whole team (default none)",
}
START_FIELDS = {
    "mode": f"one of {list(START_MODES)}",
    "p": "probability of 'reflect' in mode surrounded_and_reflect (default 0.5)",
}


@dataclass(frozen=True)
class TeamGen:
    """Per-episode unit types (SMACv2's weighted_teams); see the module docstring."""

    unit_types: tuple[str, ...]
    weights: tuple[float, ...]
    exceptions: tuple[str, ...]
    n_units: int
    n_enemies: int


@dataclass(frozen=True)
class StartPositions:
    """Per-episode start positions: `mode` in START_MODES, `p` = P(reflect) when mixed."""

    mode: str
    p: float = 0.5


def _fields(raw: Any, valid: dict[str, str], where: str) -> dict:
    if not isinstance(raw, dict):
        raise EnvError(f"{where} must be a mapping with fields {sorted(valid)}")
    for key in raw:
        if key not in valid:
            raise EnvError(f"{where}: unknown field {key!r}; valid fields: {sorted(valid)}")
    return raw


def parse_team_gen(raw: Any, n_units: Any, n_enemies: Any, types: list[str], src: str) -> TeamGen:
    """Validate a map's `team_gen` with its `n_units` / `n_enemies`; errors name the field."""
    raw = _fields(raw, TEAM_GEN_FIELDS, f"{src}: field 'team_gen'")
    for name, n in (("n_units", n_units), ("n_enemies", n_enemies)):
        if not isinstance(n, int) or isinstance(n, bool) or n < 1:
            raise EnvError(f"{src}: field {name!r} must be an int >= 1 with team_gen, got {n!r}")
    pool = raw.get("unit_types")
    if not isinstance(pool, list) or not pool or len(set(pool)) != len(pool):
        raise EnvError(f"{src}: field 'team_gen.unit_types' must be a list of distinct types")
    for t in pool:
        if t not in types:
            raise EnvError(f"{src}: field 'team_gen.unit_types': unknown unit type {t!r}; "
                           f"valid: {sorted(types)}")  # fmt: skip
    w = raw.get("weights")
    ok = isinstance(w, list) and len(w) == len(pool) and all(isinstance(x, int | float) for x in w)
    if not ok or min(w) < 0 or not math.isclose(sum(w), 1.0, abs_tol=1e-6):
        raise EnvError(f"{src}: field 'team_gen.weights' must be {len(pool)} numbers >= 0 "
                       f"summing to 1, got {w!r}")  # fmt: skip
    exc = raw.get("exception_unit_types", [])
    if not isinstance(exc, list) or not set(exc) <= set(pool):
        raise EnvError(f"{src}: field 'team_gen.exception_unit_types' must list types of "
                       f"unit_types {pool}, got {exc!r}")  # fmt: skip
    if sum(wi for t, wi in zip(pool, w, strict=True) if t not in exc) <= 0:
        raise EnvError(f"{src}: field 'team_gen.weights' gives no weight to a non-exception type")
    return TeamGen(tuple(pool), tuple(float(x) for x in w), tuple(exc), n_units, n_enemies)


def parse_start_positions(raw: Any, src: str) -> StartPositions:
    """Validate a map's `start_positions`; errors name the field and the valid modes."""
    raw = _fields(raw, START_FIELDS, f"{src}: field 'start_positions'")
    mode = raw.get("mode")
    if mode not in START_MODES:
        raise EnvError(f"{src}: field 'start_positions.mode' must be one of "
                       f"{list(START_MODES)}, got {mode!r}")  # fmt: skip
    p = raw.get("p", 0.5)
    if not isinstance(p, int | float) or not 0 <= p <= 1:
        raise EnvError(f"{src}: field 'start_positions.p' must be in [0, 1], got {p!r}")
    return StartPositions(mode, float(p))


def _draw_team(tg: TeamGen, n: int, rng: np.random.Generator) -> list[str]:
    while True:
        idx = rng.choice(len(tg.unit_types), size=n, p=tg.weights)
        team = [tg.unit_types[k] for k in idx]
        if not all(t in tg.exceptions for t in team):
            return team


def draw_teams(tg: TeamGen, rng: np.random.Generator) -> tuple[list[str], list[str]]:
    """(agent types [n_units], enemy types [n_enemies]) of one episode."""
    allies = _draw_team(tg, tg.n_units, rng)
    enemies = list(allies[: tg.n_enemies])
    if tg.n_enemies > tg.n_units:
        enemies += _draw_team(tg, tg.n_enemies - tg.n_units, rng)
    return allies, enemies


def draw_points(
    sp: StartPositions, n: int, e: int, w: float, h: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Creation points of one episode: agents [n, 2], enemies [e, 2], and each enemy's group
    [e] (the enemy attack-moves group by group, each keeping its own shape)."""
    mode = sp.mode
    if mode == "surrounded_and_reflect":
        mode = "reflect" if rng.random() <= sp.p else "surrounded"
    if mode == "reflect":
        allies = rng.uniform((0.0, 0.0), (w / 2 - 1, h), size=(n, 2))
        enemies = np.empty((e, 2))
        k = min(n, e)
        enemies[:k, 0] = w - allies[:k, 0]
        enemies[:k, 1] = allies[:k, 1]
        if e > n:
            enemies[k:] = rng.uniform((w / 2, 0.0), (w, h), size=(e - n, 2))
        return allies, enemies, np.arange(e)
    centre = np.array([w / 2, h / 2])
    corners = np.array([[0.0, 0.0], [0.0, h], [w, h], [w, 0.0]])
    near = centre + 2.0 * np.array([[-1, -1], [-1, 1], [1, 1], [1, -1]])
    n_groups = int(rng.integers(1, 5))
    sizes = rng.multinomial(e, np.ones(n_groups) / n_groups)
    frac = rng.uniform(size=n_groups)
    diag = rng.choice(4, size=n_groups, replace=False)
    pts = near[diag] * frac[:, None] + corners[diag] * (1 - frac[:, None])
    group = np.repeat(np.arange(n_groups), sizes)
    return np.tile(centre, (n, 1)), pts[group], group


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


def place(
    points: np.ndarray, radius: np.ndarray, air: np.ndarray, size, fixed: np.ndarray | None = None
) -> np.ndarray:
    """Where SC2 puts units created at `points` [n, 2] (see the module docstring): [n, 2].

    Args:
        radius / air: [n] each unit's collision radius and layer.
        size: (width, height); spots off the map are skipped.
        fixed: [n] units that keep their point (and still take up room); default none.
    """
    n = len(points)
    out = np.empty((n, 2))
    keep = np.zeros(n, np.bool_) if fixed is None else np.asarray(fixed, np.bool_)
    _place_kernel(np.asarray(points, np.float64), np.asarray(radius, np.float64),
                  np.asarray(air, np.bool_), keep, _RING, float(size[0]), float(size[1]),
                  out)  # fmt: skip
    return out


@njit(cache=True)
def _place_kernel(points, radius, air, fixed, ring, w, h, out):
    for u in range(points.shape[0]):
        if fixed[u]:
            out[u, 0], out[u, 1] = points[u, 0], points[u, 1]
            continue
        px = min(max(points[u, 0], 0.0), w - 1e-3)
        py = min(max(points[u, 1], 0.0), h - 1e-3)
        out[u, 0], out[u, 1] = px, py  # fallback: no free spot within the ring
        for k in range(ring.shape[0]):
            x, y = points[u, 0] + ring[k, 0], points[u, 1] + ring[k, 1]
            if x < 0.0 or y < 0.0 or x > w - 1e-3 or y > h - 1e-3:
                continue
            free = True
            for v in range(u):
                if air[v] == air[u]:
                    gap = radius[u] + radius[v] + 0.02
                    dx, dy = x - out[v, 0], y - out[v, 1]
                    if dx * dx + dy * dy < gap * gap:
                        free = False
                        break
            if free:
                out[u, 0], out[u, 1] = x, y
                break

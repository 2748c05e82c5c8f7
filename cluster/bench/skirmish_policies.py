"""Scripted and random team win rates on skirmish maps: `credit env scripted` (cluster/commands/
env.py) prints one JSON object (and writes it with --out).

    credit env scripted --maps bane_vs_bane bane_no_z --policy bane_charge random \
        --episodes 500 --seeds 0 --set bane_dodge=0.5 --out FILE.json
    credit env scripted --maps bane_z0 bane_z5 --sweep bane_dodge=-1,0,0.5 --episodes 500

Each (setting, map, policy) row holds the per-seed results (seed s: the envs seeded 1000 s + k,
the policy's generator seeded s) and their totals. Without --policy a map gets its default
trio: bane_charge, nearest and random on baneling maps (bane_*), focus_fire, nearest and
random on the others. --set fixes `SkirmishConfig` fields for every row; --sweep KEY=V1,V2,...
repeats everything for each value of one field.
"""

from __future__ import annotations

import numpy as np
import yaml

from actors.envs.registry import is_map_file
from actors.envs.skirmish import make_skirmish_vec
from actors.envs.skirmish.config import make_config
from actors.envs.skirmish.maps import builtin_map, load_map_file
from actors.envs.skirmish.scripts import POLICIES, evaluate
from cluster.config.schema import parse_overrides
from cluster.errors import UsageError

BANE_MAPS = ["bane_vs_bane", "bane_med", "bane_small", "bane_no_z"]
SANITY_MAPS = ["3m", "8m", "2s3z"]


def default_policies(map_name: str) -> list[str]:
    """bane_charge, nearest and random on baneling maps; focus_fire, nearest and random else."""
    first = "bane_charge" if _spec(map_name).name.startswith("bane") else "focus_fire"
    return [first, "nearest", "random"]


def parse_sweep(text: str | None) -> tuple[str | None, list]:
    """`KEY=V1,V2,...` -> (KEY, [values parsed as YAML scalars]); None -> (None, [None])."""
    if text is None:
        return None, [None]
    key, sep, raw = text.partition("=")
    values = [v.strip() for v in raw.split(",")]
    if not sep or not key.strip() or not all(values):
        raise UsageError(f"--sweep expects KEY=V1,V2,..., got {text!r}")
    return key.strip(), [yaml.safe_load(v) for v in values]


def _spec(name: str):
    """A built-in map by name, or a map file (a path ending in .yaml or .yml)."""
    return load_map_file(name) if is_map_file(name) else builtin_map(name)


def check_inputs(maps: list[str], policies: list[str] | None, episodes: int, seeds: list[int],
                 num_envs: int) -> None:  # fmt: skip
    """Name the first bad map, policy or count before anything runs."""
    for m in maps:
        _spec(m)  # EnvError naming the map (or file) and what is valid
    for p in policies or []:
        if p not in POLICIES:
            raise UsageError(f"unknown policy {p!r}; valid policies: {', '.join(POLICIES)}")
    if episodes < 1 or num_envs < 1 or not seeds:
        raise UsageError("need --episodes >= 1, --num-envs >= 1 and at least one seed")


def run_case(map_name: str, policy: str, episodes: int, seeds: list[int], options: dict,
             num_envs: int = 100) -> dict:  # fmt: skip
    """Evaluate one (map, policy) pair under `options` (SkirmishConfig fields) on each seed."""
    per_seed = []
    for s in seeds:
        where = {"map_file": map_name} if is_map_file(map_name) else {"map_name": map_name}
        venv = make_skirmish_vec(min(episodes, num_envs), seed=1000 * s, **where, **options)
        per_seed.append({"seed": s, **evaluate(venv, POLICIES[policy], episodes, seed=s)})
    keys = ("win_rate", "timeout_rate", "mean_return", "mean_length")
    means = {k: float(np.mean([r[k] for r in per_seed])) for k in keys}
    wins = round(sum(r["win_rate"] * r["episodes"] for r in per_seed))
    return {"map": map_name, "policy": policy, "settings": options,
            "episodes": episodes * len(seeds), "wins": wins, **means,
            "per_seed": per_seed}  # fmt: skip


def ladder(maps: list[str], policies: list[str] | None, episodes: int, seeds: list[int],
           sets: list[str], sweep: str | None, num_envs: int = 100) -> list[dict]:  # fmt: skip
    """All rows: for each sweep value, each map, each policy (or the map's default trio)."""
    check_inputs(maps, policies, episodes, seeds, num_envs)
    base = parse_overrides(sets)
    key, values = parse_sweep(sweep)
    settings = [dict(base) if key is None else {**base, key: v} for v in values]
    for options in settings:
        make_config(**options)  # EnvError naming a bad key or value, before anything runs
    rows = []
    for options in settings:
        for m in maps:
            for p in policies or default_policies(m):
                rows.append(run_case(m, p, episodes, seeds, options, num_envs))
    return rows


if __name__ == "__main__":  # the older `python -m cluster.bench.skirmish_policies ...` form
    import sys

    from cluster.cli import main

    sys.argv[1:1] = ["env", "scripted"]  # what the JSON records as the command
    sys.exit(main(sys.argv[1:]))

"""Scripted-policy win rates on skirmish maps; prints one JSON object (optionally --out FILE).

    python -m cluster.bench.skirmish_policies --episodes 200 --seeds 0 1 2 \
        --out results/skirmish/policies.json
    python -m cluster.bench.skirmish_policies --maps bane_z0 bane_z5 bane_z30 --out FILE

Compares "banelings charge, zerglings step back" (bane_charge) with "everyone attacks the
nearest" (nearest) on bane_vs_bane, its redundancy variants (bane_med, bane_small) and
bane_no_z, with the uniformly random policy as the floor; plus the sanity maps (3m, 8m, 2s3z:
focus_fire, nearest, random). Each (map, policy) row has the per-seed results (seed s: envs
seeded 1000 s + k, policy rng seeded s) and their means.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from actors.envs.skirmish import make_skirmish_vec
from actors.envs.skirmish.scripts import POLICIES, evaluate

BANE_MAPS = ["bane_vs_bane", "bane_med", "bane_small", "bane_no_z"]
SANITY_MAPS = ["3m", "8m", "2s3z"]


def cases(maps: list[str]) -> list[tuple[str, str]]:
    """(map, policy) pairs: bane_charge, nearest and random on baneling maps (bane_*, e.g.
    the generated bane_z<N>), focus_fire, nearest and random on the others."""
    out = []
    for m in maps:
        first = "bane_charge" if m.startswith("bane") else "focus_fire"
        out += [(m, p) for p in (first, "nearest", "random")]
    return out


def run_case(map_name: str, policy: str, episodes: int, seeds: list[int]) -> dict:
    """Evaluate one (map, policy) pair on each seed; per-seed rows plus means."""
    per_seed = []
    for s in seeds:
        venv = make_skirmish_vec(min(episodes, 100), seed=1000 * s, map_name=map_name)
        per_seed.append({"seed": s, **evaluate(venv, POLICIES[policy], episodes, seed=s)})
    keys = ("win_rate", "timeout_rate", "mean_return", "mean_length")
    means = {k: float(np.mean([r[k] for r in per_seed])) for k in keys}
    return {"map": map_name, "policy": policy, "episodes_per_seed": episodes, **means,
            "per_seed": per_seed}  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--episodes", type=int, default=200, help="episodes per seed")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--out", default=None)
    p.add_argument(
        "--maps",
        nargs="+",
        default=BANE_MAPS + SANITY_MAPS,
        help="skirmish map names (default: the four Table 5.1 maps and 3m, 8m, 2s3z)",
    )
    a = p.parse_args()
    rows = [run_case(m, pol, a.episodes, a.seeds) for m, pol in cases(a.maps)]
    record = {
        "command": " ".join(["python", *sys.argv]),
        "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "results": rows,
    }
    text = json.dumps(record, indent=2)
    print(text)
    if a.out:
        with open(a.out, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()

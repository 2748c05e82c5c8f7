"""Scripted-policy win rates on skirmish maps; prints one JSON object (optionally --out FILE).

    python bench/skirmish_policies.py --episodes 200 --out results/skirmish/policies.json

Compares "banelings charge, zerglings step back" (bane_charge) with "everyone attacks the
nearest" (nearest) on bane_vs_bane and bane_no_z, plus the 3m sanity pair.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from actors.envs.skirmish import make_skirmish_vec
from actors.envs.skirmish.scripts import POLICIES, evaluate

CASES = [
    ("bane_vs_bane", "bane_charge"),
    ("bane_vs_bane", "nearest"),
    ("bane_vs_bane", "random"),
    ("bane_no_z", "bane_charge"),
    ("bane_no_z", "nearest"),
    ("bane_no_z", "random"),
    ("3m", "focus_fire"),
    ("3m", "nearest"),
    ("3m", "random"),
]


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--episodes", type=int, default=200)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None)
    a = p.parse_args()
    rows = []
    for map_name, policy in CASES:
        venv = make_skirmish_vec(min(a.episodes, 100), seed=a.seed, map_name=map_name)
        r = evaluate(venv, POLICIES[policy], a.episodes, seed=a.seed)
        rows.append({"map": map_name, "policy": policy, **r})
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

"""`credit env list`: what environments are registered and their sizes."""

from __future__ import annotations

import argparse
import json

from actors.envs.registry import env_ids, env_info


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("env", help="inspect environments")
    env_sub = p.add_subparsers(dest="env_command", required=True, metavar="ENV_COMMAND")
    lst = env_sub.add_parser("list", help="every registered env with its sizes")
    lst.add_argument("--json", action="store_true", help="print a JSON list of objects")
    lst.set_defaults(func=cmd_list)


def env_rows() -> list[dict]:
    rows = []
    for env_id in env_ids():
        info = env_info(env_id)
        rows.append(
            {
                "id": env_id,
                "n_agents": info.n_agents,
                "n_enemies": info.n_enemies,
                "obs_shape": info.obs_shape,
                "state_shape": info.state_shape,
                "n_actions": info.n_actions,
                "episode_limit": info.episode_limit,
            }
        )
    return rows


def cmd_list(args: argparse.Namespace) -> int:
    rows = env_rows()
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    cols = ["id", "n_agents", "n_enemies", "obs_shape", "state_shape", "n_actions", "episode_limit"]
    heads = ["id", "agents", "enemies", "obs", "state", "actions", "limit"]
    widths = [max(len(h), *(len(str(r[c])) for r in rows)) for h, c in zip(heads, cols, strict=True)]
    print("  ".join(h.ljust(w) for h, w in zip(heads, widths, strict=True)))
    for r in rows:
        print("  ".join(str(r[c]).ljust(w) for c, w in zip(cols, widths, strict=True)))
    return 0

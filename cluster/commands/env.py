"""`credit env list`: what environments are registered and their sizes."""

from __future__ import annotations

import argparse
import json
import logging

from actors.envs.base import EnvError
from actors.envs.registry import env_ids, env_info
from actors.envs.skirmish.maps import BANE_VARIANT_MAX
from actors.envs.skirmish.scripts import POLICIES
from cluster.bench.common import emit
from cluster.bench.skirmish_policies import BANE_MAPS, SANITY_MAPS, ladder
from cluster.commands import add_command

log = logging.getLogger(__name__)
COLS = ["id", "n_agents", "n_enemies", "obs_shape", "state_shape", "n_actions", "episode_limit"]


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "env",
        "Print the registered environments, or write a GIF of one episode.",
    )
    env_sub = p.add_subparsers(dest="env_command", required=True, metavar="ENV_COMMAND")
    lst = add_command(
        env_sub,
        "list",
        "Print every registered env with its sizes (a table, or JSON); writes nothing.",
    )
    lst.add_argument("--json", action="store_true", help="print a JSON list of objects")
    lst.set_defaults(func=cmd_list)
    ren = add_command(
        env_sub,
        "render",
        "Play one episode with a scripted policy and write it to --out as an animated GIF"
        " (or a PNG strip).",
    )
    ren.add_argument("--env", default="skirmish/bane_vs_bane", help="a skirmish env id")
    ren.add_argument("--out", required=True, help="output .gif (or .png for a frame strip)")
    ren.add_argument("--policy", default="nearest", help=" | ".join(POLICIES))
    ren.add_argument("--seed", type=int, default=0)
    ren.add_argument("--max-steps", type=int, default=120)
    ren.add_argument("--map-file", default=None, help="map file for skirmish/custom")
    ren.set_defaults(func=cmd_render)
    register_scripted(env_sub)


def register_scripted(env_sub: argparse._SubParsersAction) -> None:
    sc = add_command(
        env_sub,
        "scripted",
        "Play scripted and random teams on skirmish maps and print their win rates as JSON"
        " (--out also writes it); --set / --sweep change simulator options.",
    )
    sc.add_argument("--maps", nargs="+", default=BANE_MAPS + SANITY_MAPS, metavar="MAP",
                    help="skirmish map names (e.g. bane_vs_bane bane_z5) or map files (.yaml, "
                    ".yml); default: the four Table 5.1 maps and 3m, 8m, 2s3z")  # fmt: skip
    sc.add_argument("--policy", nargs="+", default=None, metavar="POLICY",
                    help=f"one or more of: {', '.join(POLICIES)} (default per map: bane_charge"
                    " or focus_fire, nearest, random)")  # fmt: skip
    sc.add_argument("--episodes", type=int, default=200, help="episodes per seed")
    sc.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    sc.add_argument("--num-envs", type=int, default=100, help="battles stepped together")
    sc.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a SkirmishConfig option for every row, e.g. bane_dodge=0.5")  # fmt: skip
    sc.add_argument("--sweep", default=None, metavar="KEY=V1,V2,...",
                    help="repeat every row for each value of one option")  # fmt: skip
    sc.add_argument("--out", default=None, help="also write the JSON here")
    sc.set_defaults(func=cmd_scripted)


def env_rows() -> list[dict]:
    rows = []
    for env_id in env_ids():
        try:
            info = env_info(env_id)
        except EnvError as e:
            # e.g. smac/<map> without StarCraft II: listed, sizes unknown, reason logged.
            log.debug("%s unavailable: %s", env_id, e)
            rows.append({"id": env_id, **dict.fromkeys(COLS[1:]), "available": False})
            continue
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
    cols = COLS
    heads = ["id", "agents", "enemies", "obs", "state", "actions", "limit"]
    widths = [
        max(len(h), *(len(str(r[c])) for r in rows)) for h, c in zip(heads, cols, strict=True)
    ]
    print("  ".join(h.ljust(w) for h, w in zip(heads, widths, strict=True)))
    for r in rows:
        cells = [
            ("-" if r[c] is None else str(r[c])).ljust(w) for c, w in zip(cols, widths, strict=True)
        ]
        note = "  (unavailable: needs StarCraft II SMAC)" if r.get("available") is False else ""
        print("  ".join(cells) + note)
    print(
        "generated on request: skirmish/bane_z<N>, bane_vs_bane with N allied zerglings "
        f"(0..{BANE_VARIANT_MAX}; bane_z20 = bane_vs_bane, bane_z15 = bane_med, "
        "bane_z10 = bane_small)"
    )
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    from actors.episode_gifs import render_episode

    kwargs = {"map_file": args.map_file} if args.map_file else {}
    summary = render_episode(
        args.env, args.out, policy=args.policy, seed=args.seed, max_steps=args.max_steps, **kwargs
    )
    print(json.dumps(summary))
    return 0


def cmd_scripted(args: argparse.Namespace) -> int:
    rows = ladder(args.maps, args.policy, args.episodes, args.seeds, args.set, args.sweep,
                  args.num_envs)  # fmt: skip
    emit("env_scripted", {"results": rows}, args.out)
    return 0

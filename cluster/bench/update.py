"""`credit bench update`: the cost of one learner update of several algorithms on the same
batch, side by side.

One batch of `--batch` episodes is recorded once on `--env` with a uniformly random policy
(ε = 1); every algorithm is built from its shipped config (plus `--set` overrides) and steps on
that same batch. Rounds interleave the algorithms so that drift in the machine's load hits them
alike; the JSON has each one's median milliseconds per update, its ratio to the first
(`ratio`: the last algorithm's), and how much one update raises resident memory.
The allocator is set up as training sets it (`run.keep_freed_memory`, on by default:
`cluster.alloc`), the same for every algorithm; with it on, memory an update reuses from the
previous one is not counted in `peak_mib_per_update`.

`--profile N` also runs one more update of each algorithm under `torch.profiler` and lists
its N most expensive operators by their own CPU time (`profile`: operator, milliseconds,
calls, share of the update's operator time). Shares are what to read on a busy machine: the
milliseconds stretch with the load, the split between operators much less.
"""

from __future__ import annotations

import argparse
import gc
import os
import time
from pathlib import Path

import numpy as np
import torch

from actors.envs.registry import make_vec_env
from actors.policy import ExplorationConfig
from actors.rollout import RolloutWorker
from buffer_service.episode import EpisodeBatch
from cluster.alloc import keep_freed_memory
from cluster.bench.common import emit
from cluster.commands import add_command
from cluster.config.train import load_train_config
from cluster.errors import UsageError
from learner.registry import get_algo


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "update",
        "Time one learner update of several algorithms on the same batch and print JSON; "
        "--out also writes it.",
    )
    p.add_argument("--env", default="skirmish/3m")
    p.add_argument("--algos", default="vdn,rdn", help="comma-separated; ratios are to the first")
    p.add_argument("--batch", type=int, default=32, help="episodes per update")
    p.add_argument("--seeds", type=int, default=1, help="ensemble members (E)")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--updates", type=int, default=10, help="updates per algorithm per round")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="[ALGO:]KEY=VALUE",
        help="config override; with ALGO: for that algorithm only",
    )
    p.add_argument(
        "--profile",
        type=int,
        default=0,
        metavar="N",
        help="also profile one update per algorithm and list its N costliest operators",
    )
    p.add_argument("--out", help="also write the JSON here")
    p.set_defaults(func=cmd_update)


def record_batch(env: str, episodes: int, seeds: int) -> EpisodeBatch:
    """`episodes` random-policy episodes per member, stacked [E, B, ...] (or [B, ...])."""
    venv = make_vec_env(env, episodes * seeds, seed=0)
    schema = venv.info.schema()
    cfg = load_train_config("vdn", env, [], [])
    agent = cfg.algo.agent.build(seeds, schema)
    worker = RolloutWorker(venv, agent, "q", ExplorationConfig(1.0, 1.0, 1), seeds)
    eps = worker.run_round(t_env=0).episodes
    if seeds == 1:
        return EpisodeBatch.from_episodes(eps)
    return EpisodeBatch.from_members([eps[k * episodes : (k + 1) * episodes] for k in range(seeds)])


def _status_kib(field: str) -> int | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except OSError:
        pass
    return None


def update_peak_mib(learner, batch: EpisodeBatch) -> float | None:
    """How far one update raises the process's resident memory above where it started
    (Linux: the peak-RSS mark is reset through /proc/self/clear_refs, then read back as
    VmHWM); None where that is not available. Memory the allocator kept from earlier work
    and reuses is not counted, so this is a lower bound of the update's working set."""
    gc.collect()
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return None
    base = _status_kib("VmRSS")
    learner.step(batch)
    top = _status_kib("VmHWM")
    if base is None or top is None:
        return None
    return round(max(0, top - base) / 1024, 1)


def overrides_for(algo: str, overrides: list[str]) -> list[str]:
    """The --set values that apply to `algo`: unprefixed ones and those prefixed `algo:`."""
    out = []
    for o in overrides:
        head, sep, rest = o.partition(":")
        if not sep or "=" in head:
            out.append(o)
        elif head == algo:
            out.append(rest)
    return out


def profile_update(learner, batch: EpisodeBatch, top: int) -> list[dict]:
    """One update under torch.profiler: its `top` operators by self CPU time, each with its
    milliseconds, number of calls and share of the self time of every operator."""
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        learner.step(batch)
    ops = [ev for ev in prof.key_averages() if ev.key.startswith("aten::")]
    total = sum(ev.self_cpu_time_total for ev in ops) or 1.0
    ops.sort(key=lambda ev: ev.self_cpu_time_total, reverse=True)
    return [
        {
            "op": ev.key,
            "self_ms": round(ev.self_cpu_time_total / 1000, 2),
            "calls": int(ev.count),
            "share": round(ev.self_cpu_time_total / total, 4),
        }
        for ev in ops[:top]
    ]


def cmd_update(args: argparse.Namespace) -> int:
    algos = [a for a in args.algos.split(",") if a]
    if not algos:
        raise UsageError("--algos must name at least one algorithm")
    for a in algos:
        try:
            get_algo(a)
        except ValueError as e:
            raise UsageError(str(e)) from None
    if args.profile < 0:
        raise UsageError(f"--profile must be >= 0, got {args.profile}")
    torch.set_num_threads(1)
    learners, cfgs = {}, {}
    for a in algos:
        cfgs[a] = load_train_config(a, args.env, [], overrides_for(a, args.set))
    # the allocator is process-wide: every algorithm runs under the same setting
    keep = {cfgs[a].run.keep_freed_memory for a in algos}
    if len(keep) != 1:
        raise UsageError("run.keep_freed_memory must be the same for every algorithm")
    kept = keep_freed_memory() if keep.pop() else False
    batch = record_batch(args.env, args.batch, args.seeds)
    for a in algos:
        cfg = cfgs[a]
        learner = get_algo(a).build(
            cfg.algo, make_vec_env(args.env, 1).info.schema(), args.seeds, "cpu"
        )
        learner.step(batch)  # warm-up: allocator and first-call costs out of the timing
        learners[a] = learner
    peak = {a: update_peak_mib(learner, batch) for a, learner in learners.items()}
    times: dict[str, list[float]] = {a: [] for a in algos}
    for _ in range(args.rounds):
        for a, learner in learners.items():
            started = time.perf_counter()
            for _ in range(args.updates):
                learner.step(batch)
            times[a].append((time.perf_counter() - started) / args.updates * 1000)
    ms = {a: round(float(np.median(v)), 2) for a, v in times.items()}
    first = algos[0]
    extra = {}
    if args.profile:
        extra["profile"] = {a: profile_update(m, batch, args.profile) for a, m in learners.items()}
    emit(
        "update",
        {
            "env": args.env,
            "batch_episodes": args.batch,
            "batch_steps": int(batch.reward.shape[-1]),
            "seeds": args.seeds,
            "overrides": args.set,
            "ms_per_update": ms,
            f"ratio_to_{first}": {a: round(ms[a] / ms[first], 2) for a in algos},
            "ratio": round(ms[algos[-1]] / ms[first], 2),  # the last algo's to the first's
            "peak_mib_per_update": peak,
            "keep_freed_memory": kept,
            "rounds_ms": {a: [round(x, 2) for x in v] for a, v in times.items()},
            "load_avg_1m": os.getloadavg()[0],
            **extra,
        },
        args.out,
    )
    return 0

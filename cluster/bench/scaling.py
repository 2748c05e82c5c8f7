"""`credit bench scaling`: steady-state throughput of the real cluster against actor count.

For every actor count N, three configurations run one after the other on one private Ray
instance (started once, on 127.0.0.1, declaring every CPU of the machine; each actor
reserves cpus / max(N) of them, so the largest count fits, e.g. 0.5 CPU each for 4 actors
on 2 cores; Ray's CPU count is a scheduling label, not a limit):

* ``no_learner``: the real rollout actors acting with the untrained (version 0) policy and
  inserting into the real buffer service with the sample-to-insert limiter off; nobody
  samples or trains. The env-stepping bound.
* ``train``: `ClusterTrainer.train()` as `credit train --mode cluster` runs it (huge t_max,
  one evaluation at the start, no checkpoints, no Prometheus exporters), on a thread of
  this process while the main thread takes the snapshots.
* ``transport``: `SyntheticActor`s insert pre-built random episodes of the env's schema
  (the no-learner bound's mean length) through the same coordinator sync and buffer client,
  limiter off, while a learner-side client samples batches as fast as it is served. The
  transport bound (Ray RPC, msgpack, TCP, the service's validation, log and fsync).

Each configuration warms up (until data flows, then `--warmup` seconds) and is measured in
`--windows` equal windows over `--duration` seconds; the JSON has every window and their
median. Rates come from cumulative counters read between windows; CPU from /proc.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import threading
import time
from dataclasses import replace
from itertools import pairwise
from pathlib import Path
from typing import Any

from buffer_service.client import BufferClient
from buffer_service.config import RateLimiterConfig, TableConfig
from cluster.bench import scaling_stats as st
from cluster.bench.common import emit
from cluster.commands import add_command

log = logging.getLogger(__name__)

MODES = ("no_learner", "train", "transport")


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "scaling",
        "Measure cluster throughput, CPU use and policy lag against the number of actors;"
        " writes OUT/scaling.json and OUT/scaling.png.",
    )
    p.add_argument("--env", default="skirmish/3m", help="env id")
    p.add_argument("--algo", default="rdn", help="learner algorithm")
    p.add_argument("--actors", default="1,2,4", help="comma-separated actor counts")
    p.add_argument("--duration", type=float, default=60.0, help="measured seconds per config")
    p.add_argument("--windows", type=int, default=3, help="measurement windows (>= 3)")
    p.add_argument("--warmup", type=float, default=10.0, help="seconds after data flows")
    p.add_argument("--modes", default=",".join(MODES), help="subset of " + ",".join(MODES))
    p.add_argument("--no-fsync", action="store_true", help="buffer service without fsync")
    p.add_argument("--set", action="append", default=[], help="config override key=value")
    p.add_argument("--out", required=True, help="folder for scaling.json and scaling.png")
    p.set_defaults(func=cmd_scaling)


def limiter_off(tables: tuple[TableConfig, ...]) -> tuple[TableConfig, ...]:
    """The same tables with the sample-to-insert ratio off (a plain min-size limiter)."""
    return tuple(
        replace(
            t,
            rate_limiter=RateLimiterConfig(
                min_size_to_sample=t.rate_limiter.min_size_to_sample, samples_per_insert=0.0
            ),
        )
        for t in tables
    )


class Probe:
    """Takes the snapshots `scaling_stats.window_figures` compares.

    Args:
        coordinator: the Coordinator actor (progress counters).
        actors: the actor handles (their `stats`).
        buffer: the BufferProcess (pid, address).
        learner_stats: a LoopStats of the learner loop (or the transport sampler).
    """

    def __init__(self, coordinator, actors: list, buffer, learner_stats):
        self.coordinator, self.actors, self.buffer = coordinator, actors, buffer
        self.learner_stats = learner_stats
        self.client = BufferClient(buffer.host, buffer.port, token=buffer.token, max_retries=100)

    def snapshot(self) -> dict[str, Any]:
        import ray

        progress = self.coordinator.progress.remote()
        actor_stats = [a.stats.remote() for a in self.actors]
        report = ray.get(progress, timeout=60)
        t_env, episodes = report.t_env, report.episodes
        actors = [a.as_dict() for a in ray.get(actor_stats, timeout=60)]
        buffer = self.client.stats()
        learner = self.learner_stats.snapshot()
        table = st.process_table()
        with open("/proc/stat") as f:
            machine = st.parse_machine_stat(f.read())
        now = time.monotonic()
        cpu = st.group_ticks(table, os.getpid(), self.buffer.pid, [a["pid"] for a in actors])
        return {
            "t": now,
            "t_env": t_env,
            "episodes": episodes,
            "learner": learner,
            "buffer": buffer,
            "actors": actors,
            "cpu_ticks": cpu,
            "machine_ticks": machine,
        }

    def close(self) -> None:
        self.client.close()


def measure(probe: Probe, args: argparse.Namespace, started, failed) -> dict[str, Any]:
    """Wait for `started()` (data flows), warm up, then take `args.windows` windows.

    Args:
        probe: the snapshot taker.
        args: duration, windows, warmup.
        started: () -> bool, true once the configuration is in steady operation.
        failed: () -> BaseException | None, the configuration's background failure.

    Returns:
        {"windows": [figures...], "median": figures, "mean_episode_len": steps/episode}
    """
    deadline = time.monotonic() + 600
    while not started():
        if failed() is not None:
            raise RuntimeError("the configuration failed while starting") from failed()
        if time.monotonic() > deadline:
            raise RuntimeError("no data flowed within 600 s")
        time.sleep(0.5)
    time.sleep(args.warmup)
    clk, ncpu = os.sysconf("SC_CLK_TCK"), os.cpu_count() or 1
    snaps = [probe.snapshot()]
    for _ in range(args.windows):
        time.sleep(args.duration / args.windows)
        snaps.append(probe.snapshot())
        if failed() is not None:
            raise RuntimeError("the configuration failed while measured") from failed()
    windows = [st.window_figures(a, b, clk, ncpu) for a, b in pairwise(snaps)]
    steps = snaps[-1]["t_env"] - snaps[0]["t_env"]
    eps = snaps[-1]["episodes"] - snaps[0]["episodes"]
    return {
        "median": st.median_tree(windows),
        "windows": windows,
        "mean_episode_len": steps / eps if eps else None,
    }


def _config(args: argparse.Namespace, n: int, actor_cpus: float):
    from cluster.config.train import load_train_config

    sets = [
        "run.t_max=1000000000000",
        "run.test_interval=1000000000000",  # one greedy evaluation, at the start
        "run.test_episodes=2",
        "run.save_interval=0",
        f"cluster.actors={n}",
        f"cluster.actor_cpus={actor_cpus}",
        "cluster.metrics=false",  # no exporters, no file-SD file shared with other runs
        f"cluster.fsync={'false' if args.no_fsync else 'true'}",
        *args.set,
    ]
    return load_train_config(args.algo, args.env, [], sets)


def run_trainer(cfg, work: Path, args: argparse.Namespace, train: bool) -> dict[str, Any]:
    """The `train` configuration (train=True) or the `no_learner` bound (train=False)."""
    import ray

    from cluster.launch.cluster import ClusterTrainer
    from cluster.process import configure

    configure(cfg.run)
    trainer = ClusterTrainer(cfg, work)
    if not train:
        trainer.buffer.tables = limiter_off(trainer.buffer.tables)
    errors: list[BaseException] = []

    def loop() -> None:
        try:
            trainer.train()
        except BaseException as e:  # reported by the main thread
            errors.append(e)

    thread = threading.Thread(target=loop, name="learner", daemon=True)
    probe = None
    try:
        trainer.start()
        probe = Probe(trainer.coordinator, trainer.actors, trainer.buffer, trainer.stats)
        if train:
            thread.start()
            started = lambda: trainer.stats.updates > 0  # noqa: E731
        else:
            progress = trainer.coordinator.progress
            started = lambda: ray.get(progress.remote()).t_env > 0  # noqa: E731
        result = measure(probe, args, started, lambda: errors[0] if errors else None)
    finally:
        trainer.stop_requested = True
        if thread.is_alive():
            thread.join(120)
        if probe:
            probe.close()
        trainer.shutdown()
        if trainer.coordinator is not None:
            ray.kill(trainer.coordinator)  # shutdown() leaves it; this Ray instance lives on
    result["setup"] = {
        "rate_limiter": "on" if train else "off",
        "num_envs_per_actor": cfg.run.num_envs,
        "batch_size": trainer.plan.batch_size,
        "tables": [t.name for t in trainer.buffer.tables],
    }
    return result


def run_transport(cfg, work: Path, args: argparse.Namespace, length: int) -> dict[str, Any]:
    """The no-env transport bound with `cfg.cluster.actors` synthetic actors."""
    import ray

    from cluster.bench.scaling_actors import Sampler, SyntheticActor
    from cluster.config.plan import data_plan
    from cluster.launch.buffer_proc import BufferProcess
    from cluster.launch.ray_actors import Coordinator

    ccfg = cfg.cluster
    plan = data_plan(cfg, ccfg.actors)
    from actors.envs.registry import make_vec_env

    schema = make_vec_env(cfg.env.id, 1, seed=0, **cfg.env.args).info.schema()
    buffer = BufferProcess(limiter_off(plan.tables), schema, work / "buffer", ccfg.fsync, False)
    buffer.start()
    coordinator = Coordinator.remote(0, 0)
    address = (buffer.host, buffer.port, buffer.token)
    actors = [
        SyntheticActor.options(num_cpus=ccfg.actor_cpus).remote(
            i, schema.to_dict(), length, cfg.run.num_envs, address, coordinator
        )
        for i in range(ccfg.actors)
    ]
    client = BufferClient(buffer.host, buffer.port, token=buffer.token, schema=schema)
    sampler = Sampler(client, plan.table, plan.batch_size)
    loops = [a.run.remote() for a in actors]
    probe = Probe(coordinator, actors, buffer, sampler.stats)
    try:
        sampler.start()
        result = measure(probe, args, lambda: sampler.stats.consumed_env_steps > 0, lambda: None)
    finally:
        ray.get(coordinator.request_stop.remote())
        ray.wait(loops, num_returns=len(loops), timeout=10)
        sampler.stop()
        probe.close()
        for a in actors:
            ray.kill(a, no_restart=True)
        ray.kill(coordinator)
        buffer.stop()
    result["setup"] = {"synthetic_episode_len": length}
    return result


def run_all(args: argparse.Namespace, counts: list[int], work: Path) -> dict[str, Any]:
    """Every configuration for every actor count; returns {mode: {N: result}}."""
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    actor_cpus = round(min(1.0, (os.cpu_count() or 1) / max(counts)), 3)
    runs: dict[str, dict[int, Any]] = {m: {} for m in MODES if m in modes}
    length = None
    for n in counts:
        cfg = _config(args, n, actor_cpus)
        for mode in runs:
            folder = work / f"{mode}_{n}"
            log.info("scaling: %s with %d actors", mode, n)
            if mode == "transport":
                length = length or _episode_len(runs, cfg)
                runs[mode][n] = run_transport(cfg, folder, args, length)
            else:
                runs[mode][n] = run_trainer(cfg, folder, args, train=mode == "train")
            shutil.rmtree(folder, ignore_errors=True)
            med = runs[mode][n]["median"]
            log.info(
                "scaling: %s N=%d insert %.0f steps/s, learner %.0f steps/s, %.2f cores",
                mode,
                n,
                med["insert_env_steps_per_s"],
                med["learner_env_steps_per_s"],
                med["cpu_cores"]["total"],
            )
    return {"runs": runs, "actor_cpus": actor_cpus}


def _episode_len(runs: dict, cfg) -> int:
    """The synthetic episodes' length: the mean measured so far (no-learner bound first),
    else the env's episode limit."""
    for mode in ("no_learner", "train"):
        for result in runs.get(mode, {}).values():
            if result.get("mean_episode_len"):
                return max(1, round(result["mean_episode_len"]))
    from actors.envs.registry import make_vec_env

    return make_vec_env(cfg.env.id, 1, seed=0, **cfg.env.args).info.episode_limit


def summarize(runs: dict[str, dict[int, Any]]) -> dict[str, Any]:
    """Per actor count, the headline medians, and efficiency T(N)/(N·T(1)) per series."""
    series = {
        "insert": ("train", "insert_env_steps_per_s"),
        "learner": ("train", "learner_env_steps_per_s"),
        "no_learner_insert": ("no_learner", "insert_env_steps_per_s"),
        "transport_insert": ("transport", "insert_env_steps_per_s"),
        "transport_sample": ("transport", "learner_env_steps_per_s"),
    }
    throughput, eff = {}, {}
    for name, (mode, key) in series.items():
        if mode not in runs or not runs[mode]:
            continue
        t = {n: r["median"][key] for n, r in runs[mode].items()}
        throughput[name] = t
        eff[name] = st.efficiency(t)
    return {"throughput_env_steps_per_s": throughput, "efficiency": eff}


def cmd_scaling(args: argparse.Namespace) -> int:
    counts = sorted({int(x) for x in args.actors.split(",") if x.strip()})
    if not counts or counts[0] < 1:
        raise SystemExit("--actors needs positive counts, e.g. 1,2,4")
    if args.windows < 3:
        raise SystemExit("--windows must be >= 3")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    work = out / ".work"
    from cluster.launch import ray_cluster

    ray_cluster.apply_ray_environment()  # before anything imports ray
    import ray

    ncpu = os.cpu_count() or 1
    where = ray_cluster.connect(None, num_cpus=ncpu)
    log.info("%s", where)
    try:
        done = run_all(args, counts, work)
    finally:
        ray.shutdown()
        shutil.rmtree(work, ignore_errors=True)
    figures = {
        "env": args.env,
        "algo": args.algo,
        "actors": counts,
        "duration_s": args.duration,
        "windows": args.windows,
        "warmup_s": args.warmup,
        "fsync": not args.no_fsync,
        "ray_num_cpus": ncpu,
        "actor_cpus": done["actor_cpus"],
        "overrides": args.set,
        **summarize(done["runs"]),
        "runs": {m: {str(n): r for n, r in rs.items()} for m, rs in done["runs"].items()},
    }
    figures = st.rounded(figures)
    from cluster.bench.scaling_plot import plot

    plot(figures, out / "scaling.png")
    emit("scaling", figures, out=str(out / "scaling.json"))
    return 0

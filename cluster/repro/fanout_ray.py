"""The Ray side of `cluster.repro.fanout`: every (algorithm, env) pair as one Ray task on the
cluster at `--address`, its events collected through a small actor.

By default the driver ships its own `actors`, `buffer_service`, `learner` and `cluster`
packages to every node for this job (Ray `runtime_env` `py_modules`), so the nodes run the
very code the driver runs, whatever they have installed; they still need the dependencies
(torch, numpy, ray of the driver's version). With `ship_code=False` the nodes import the
`credit` installed in their own environment.

Imports Ray: import this module only through `cluster.repro.fanout.run_pairs` (which sets Ray's
environment first, `cluster.launch.ray_cluster.apply_ray_environment`).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from typing import Any

from cluster.launch import ray_cluster
from cluster.launch.ray_cluster import ClusterError
from cluster.repro.pairs import POLL_S, Collector, FanOutConfig, Pair, PairEvent, PairFn, run_pair

log = logging.getLogger(__name__)


def runtime_env(ship_code: bool) -> dict | None:
    """Ray job runtime environment shipping our four packages to every node (or None)."""
    if not ship_code:
        return None
    import actors
    import buffer_service
    import cluster
    import learner

    dirs = [os.path.dirname(m.__file__) for m in (actors, buffer_service, learner, cluster)]
    return {"py_modules": dirs, "excludes": ["__pycache__", "*.pyc"]}


class _Board:
    """Ray actor (no CPU) holding the pairs' events until the driver takes them: a task
    cannot call back into the driver, and a pair on another node cannot write its files."""

    def __init__(self) -> None:
        self.events: list[PairEvent] = []

    def put(self, event: PairEvent) -> None:
        self.events.append(event)

    def take(self) -> list[PairEvent]:
        out, self.events = self.events, []
        return out

    def flush(self) -> None:
        """Nothing: a caller waits on it to know its earlier calls have run."""


class _BoardSink:
    def __init__(self, board: Any):
        self.board = board

    def put(self, event: PairEvent) -> None:
        self.board.put.remote(event)  # Ray runs one caller's calls to an actor in order


def _ray_pair(fn: PairFn, pair: Pair, args: tuple, board: Any) -> Any:
    """The body of a pair's Ray task."""
    import ray

    result = run_pair(fn, pair, args, _BoardSink(board))
    # Every event is on the board before the driver sees the result: this call runs after
    # this task's earlier puts.
    ray.get(board.flush.remote())
    return result


def run_ray(
    fn: PairFn,
    pairs: Sequence[Pair],
    args: tuple,
    cfg: FanOutConfig,
    collector: Collector,
    arrived: Callable[[Pair, Any], None],
) -> list:
    """Every pair as a Ray task on the cluster at `cfg.address`; results in `pairs` order,
    each handed to `arrived` as it comes (see `cluster.repro.fanout.run_pairs`)."""
    ray_cluster.apply_ray_environment()  # before `import ray`: it reads them at import
    import ray
    from ray.exceptions import RayError, RayTaskError
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    where = ray_cluster.connect(cfg.address, num_cpus=1, runtime_env=runtime_env(cfg.ship_code))
    pending: list = []
    try:
        _check_resources(ray.nodes(), cfg.cpus_per_pair)
        log.info("%s; %d pairs as Ray tasks of %g CPUs each", where, len(pairs), cfg.cpus_per_pair)
        # The board lives on the driver's node: the run's output is there, and that node
        # stays up as long as the driver does.
        here = NodeAffinitySchedulingStrategy(ray.get_runtime_context().get_node_id(), soft=True)
        board = ray.remote(num_cpus=0)(_Board).options(scheduling_strategy=here).remote()
        task = ray.remote(_ray_pair).options(
            num_cpus=cfg.cpus_per_pair, max_retries=cfg.max_retries, retry_exceptions=False
        )
        refs = {task.remote(fn, p, args, board): p for p in pairs}
        results: dict[Pair, Any] = {}
        pending = list(refs)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1, timeout=POLL_S)
            for event in ray.get(board.take.remote()):
                collector.handle(event)
            collector.tick()
            for ref in ready:
                try:
                    results[refs[ref]] = ray.get(ref)
                except RayTaskError:
                    raise  # the pair's own exception (also an instance of its class)
                except RayError as e:  # lost more often than retried, or never started
                    raise ClusterError(
                        f"pair {refs[ref].label} did not run to the end on the cluster (a "
                        f"lost worker is retried {cfg.max_retries} times, --max-retries): "
                        f"{type(e).__name__}: {e}"
                    ) from None
                arrived(refs[ref], results[refs[ref]])
        return [results[p] for p in pairs]
    finally:
        for ref in pending:  # an error or Ctrl-C: stop the pairs still running
            ray.cancel(ref, force=True)
        ray.shutdown()


def _check_resources(nodes: list[dict], cpus_per_pair: float) -> None:
    """Warn when no live node offers `cpus_per_pair` CPUs: Ray then waits (an autoscaler
    may add such a node) rather than fail."""
    most = max((n["Resources"].get("CPU", 0.0) for n in nodes if n.get("Alive")), default=0.0)
    if most < cpus_per_pair:
        log.warning(
            "no node of this cluster has %g CPUs (the largest has %g); the pairs wait until "
            "one joins (lower --cpus-per-pair, or add nodes)",
            cpus_per_pair,
            most,
        )

"""Run the (algorithm, env) pairs of a `credit repro` experiment: in a local process pool (no
`--address`, the default) or as Ray tasks across a cluster's nodes (`--address auto` or
`--address HOST:PORT`).

Both ways report through one collector in the driver. Each pair's process sends a `started`
event, then one `evaluated` event per evaluation (a JSON line); the driver writes those lines
to OUT/evals/<env>__<algo>.jsonl as they arrive, so a pair on another node leaves its log in
the driver's output folder and a run that dies leaves every evaluation it made. The driver
logs one line per pair as it starts (where), restarts, and finishes (wall time).

On a cluster every pair is one Ray task asking for `cpus_per_pair` CPUs. Ray retries a task
whose worker process or node dies (`max_retries`); the retry starts the pair again from
scratch with the same seeds, so its result is the one an uninterrupted run gives, and the
collector drops the lost attempt's log lines. An exception raised by the pair itself (a bad
config, a non-finite loss) is not retried: it ends the run, as it does locally.

By default the driver ships its own `actors`, `buffer_service`, `learner` and `cluster`
packages to every node (Ray `runtime_env` `py_modules`), so the nodes run the very code the
driver runs; they still need the dependencies (torch, numpy, ray) installed. With
`ship_code=False` the nodes import the `credit` installed in their own environment.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import queue
import socket
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, TypeVar

from cluster.ray_cluster import ClusterError

log = logging.getLogger(__name__)

R = TypeVar("R")
POLL_S = 1.0  # how often the driver collects events while pairs run


@dataclass(frozen=True)
class Pair:
    """One (algorithm, env) run of an experiment (all its seeds batched in one trainer)."""

    algo: str
    env: str

    @property
    def key(self) -> str:
        """File stem of the pair's evaluation log: `<env with - for />__<algo>`."""
        return f"{self.env.replace('/', '-')}__{self.algo}"

    @property
    def label(self) -> str:
        return f"{self.algo}@{self.env}"


@dataclass(frozen=True)
class FanOutConfig:
    """Where the pairs run.

    Args:
        workers: local mode: processes running pairs in parallel (1 = in this process).
        address: None = local mode; "auto" = the cluster `credit cluster up` recorded (else
            Ray's own discovery); "host:port" = that Ray head.
        cpus_per_pair: Ray mode: CPUs each pair's task asks for (its torch threads are
            `run.torch_threads`, 1 by default; ask for as many CPUs as it uses).
        max_retries: Ray mode: times a pair is restarted after its worker process or node dies.
        ship_code: Ray mode: upload this driver's packages to every node (module docstring).
    """

    workers: int = 2
    address: str | None = None
    cpus_per_pair: float = 1.0
    max_retries: int = 3
    ship_code: bool = True

    def validate(self) -> None:
        """Raise ValueError for a setting no run could use."""
        if self.workers < 1:
            raise ValueError(f"--workers must be >= 1, got {self.workers}")
        if self.cpus_per_pair <= 0:
            raise ValueError(f"--cpus-per-pair must be > 0, got {self.cpus_per_pair}")
        if self.max_retries < 0:
            raise ValueError(f"--max-retries must be >= 0, got {self.max_retries}")


@dataclass(frozen=True)
class PairEvent:
    """What a pair's process tells the driver while it runs.

    Args:
        pair: the pair.
        kind: "started" (a new attempt at the pair), "evaluated" or "finished" (the last
            event of an attempt that returned its result).
        attempt: "<host>:<pid>:<start time ns>" of the attempt, so that lines of an attempt
            that died are told from the retry's.
        text: "evaluated": one JSON line of the pair's evaluation log.
        wall_s: "finished": seconds the attempt took.
    """

    pair: Pair
    kind: str
    attempt: str
    text: str = ""
    wall_s: float = 0.0


class EventSink(Protocol):
    """Where a pair's process puts its events: `sink.put(event)`, in order."""

    def put(self, event: PairEvent) -> None: ...


class Reporter:
    """The pair function's side: `report(line)` per evaluation after `start()`."""

    def __init__(self, sink: EventSink, pair: Pair):
        self.sink, self.pair = sink, pair
        self.attempt = f"{socket.gethostname()}:{os.getpid()}:{time.time_ns()}"

    def start(self) -> None:
        self.sink.put(PairEvent(self.pair, "started", self.attempt))

    def __call__(self, line: str) -> None:
        self.sink.put(PairEvent(self.pair, "evaluated", self.attempt, line))


PairFn = Callable[..., Any]  # fn(algo, env, *args, report=Callable[[str], None]) -> result


def run_pair(fn: PairFn, pair: Pair, args: tuple, sink: EventSink) -> Any:
    """Run one pair in this process, reporting to `sink`; returns fn's result."""
    report = Reporter(sink, pair)
    report.start()
    started = time.monotonic()
    result = fn(pair.algo, pair.env, *args, report=report)
    wall = time.monotonic() - started
    sink.put(PairEvent(pair, "finished", report.attempt, wall_s=wall))
    return result


class Collector:
    """The driver's side: writes each pair's evaluation log and logs its start and finish."""

    def __init__(self, pairs: Sequence[Pair], log_dir: Path | None):
        self.log_dir, self.total = log_dir, len(pairs)
        self.attempt: dict[Pair, str] = {}
        self.starts: dict[Pair, int] = {}
        self.finished: set[Pair] = set()

    def handle(self, event: PairEvent) -> None:
        pair = event.pair
        if event.kind == "started":
            self.attempt[pair] = event.attempt
            self.starts[pair] = self.starts.get(pair, 0) + 1
            if self.log_dir is not None:  # a retry starts its log afresh
                (self.log_dir / f"{pair.key}.jsonl").write_text("")
            host, pid, _ = event.attempt.split(":")
            again = self.starts[pair] > 1
            log.info(
                "pair %s %s on %s (pid %s)%s",
                pair.label,
                "restarted" if again else "started",
                host,
                pid,
                f", attempt {self.starts[pair]}: the previous one was lost" if again else "",
            )
        elif event.attempt != self.attempt.get(pair):
            return  # a lost attempt's late event
        elif event.kind == "evaluated" and self.log_dir is not None:
            with open(self.log_dir / f"{pair.key}.jsonl", "a") as f:
                f.write(event.text.rstrip("\n") + "\n")
        elif event.kind == "finished":
            self.finished.add(pair)
            log.info(
                "pair %s finished in %.0f s (%d/%d pairs done)",
                pair.label,
                event.wall_s,
                len(self.finished),
                self.total,
            )


def run_pairs(
    fn: PairFn,
    pairs: Sequence[Pair],
    args: tuple,
    cfg: FanOutConfig,
    log_dir: Path | None = None,
    on_result: Callable[[Pair, Any], None] | None = None,
) -> list:
    """Run `fn(pair.algo, pair.env, *args, report=...)` for every pair where `cfg` says.

    Args:
        fn: a module-level function (it is pickled by reference to reach other processes).
        pairs: the pairs, in the order of the returned results.
        args: the arguments every pair gets after (algo, env).
        cfg: where to run them.
        log_dir: folder for the evaluation logs, None for none.
        on_result: called in the driver with each pair's result as it arrives.

    Returns:
        fn's results, one per pair in `pairs` order.

    Raises ClusterError when the cluster cannot be reached or a pair is lost more than
    `cfg.max_retries` times; an exception of `fn` itself is raised as it is.
    """
    collector = Collector(pairs, log_dir)
    arrived = on_result or (lambda pair, result: None)
    if cfg.address:
        return _run_ray(fn, pairs, args, cfg, collector, arrived)
    if cfg.workers <= 1:
        results = []
        for p in pairs:
            results.append(run_pair(fn, p, args, _Direct(collector)))
            arrived(p, results[-1])
        return results
    return _run_pool(fn, pairs, args, cfg.workers, collector, arrived)


class _Direct:
    """A sink handing events straight to the collector (pairs run in the driver)."""

    def __init__(self, collector: Collector):
        self.collector = collector

    def put(self, event: PairEvent) -> None:
        self.collector.handle(event)


_pool_events: Any = None  # the event queue of a local pool's worker process


def _pool_init(events: Any) -> None:
    global _pool_events
    _pool_events = events


def _pool_pair(fn: PairFn, pair: Pair, args: tuple) -> Any:
    return run_pair(fn, pair, args, _pool_events)


def _drain_queue(events: Any, collector: Collector, block_s: float = 0.0) -> None:
    """Hand every queued event to the collector, waiting up to `block_s` for each."""
    while True:
        try:
            collector.handle(events.get(timeout=block_s) if block_s else events.get_nowait())
        except queue.Empty:
            return


def _run_pool(
    fn: PairFn,
    pairs: Sequence[Pair],
    args: tuple,
    workers: int,
    collector: Collector,
    arrived: Callable[[Pair, Any], None],
) -> list:
    """Today's local mode: a process pool of `workers`; events come back on a queue the
    workers inherit."""
    events = multiprocessing.get_context().Queue()
    with ProcessPoolExecutor(workers, initializer=_pool_init, initargs=(events,)) as pool:
        futures = {pool.submit(_pool_pair, fn, p, args): p for p in pairs}
        pending = set(futures)
        while pending:
            ready, pending = wait(pending, timeout=POLL_S, return_when=FIRST_COMPLETED)
            _drain_queue(events, collector)
            for f in ready:
                arrived(futures[f], f.result())  # raises the pair's exception here
    # A worker puts its last events before it returns, but the queue's feeder thread may
    # deliver them after the result: wait for every pair's "finished".
    while len(collector.finished) < len(pairs):
        before = len(collector.finished)
        _drain_queue(events, collector, block_s=10.0)
        if len(collector.finished) == before:
            log.warning("the local workers' last events did not arrive; logs may be short")
            break
    return [f.result() for f in futures]


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


def _run_ray(
    fn: PairFn,
    pairs: Sequence[Pair],
    args: tuple,
    cfg: FanOutConfig,
    collector: Collector,
    arrived: Callable[[Pair, Any], None],
) -> list:
    """Every pair as a Ray task on the cluster at `cfg.address`."""
    from cluster import ray_cluster

    ray_cluster.apply_ray_environment()  # before `import ray`: it reads them at import
    import ray
    from ray.exceptions import RayError, RayTaskError

    where = ray_cluster.connect(cfg.address, num_cpus=1, runtime_env=runtime_env(cfg.ship_code))
    pending: list = []
    try:
        _check_resources(ray.nodes(), cfg.cpus_per_pair)
        log.info("%s; %d pairs as Ray tasks of %g CPUs each", where, len(pairs), cfg.cpus_per_pair)
        board = ray.remote(num_cpus=0)(_Board).remote()
        task = ray.remote(_ray_pair).options(
            num_cpus=cfg.cpus_per_pair, max_retries=cfg.max_retries, retry_exceptions=False
        )
        refs = {task.remote(fn, p, args, board): p for p in pairs}
        pending = list(refs)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1, timeout=POLL_S)
            for event in ray.get(board.take.remote()):
                collector.handle(event)
            for ref in ready:
                try:
                    arrived(refs[ref], ray.get(ref))
                except RayTaskError:
                    raise  # the pair's own exception (also an instance of its class)
                except RayError as e:
                    raise ClusterError(
                        f"pair {refs[ref].label} was lost {cfg.max_retries + 1} times "
                        f"(--max-retries {cfg.max_retries}): {e}"
                    ) from None
        return ray.get(list(refs))
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

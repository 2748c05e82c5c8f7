"""Run the (algorithm, env) pairs of a `credit repro` experiment: in a local process pool (no
`--address`, the default) or as Ray tasks across a cluster's nodes (`--address auto` or
`--address HOST:PORT`).

Both ways report through one collector in the driver. Each pair's process sends a `started`
event, then one `evaluated` event per evaluation (a JSON line); the driver writes those lines
to OUT/evals/<env>__<algo>.jsonl as they arrive, so a pair on another node leaves its log in
the driver's output folder and a run that dies leaves every evaluation it made. The driver
logs one line per pair as it starts (where), restarts, and finishes (wall time).

On a cluster every pair is one Ray task asking for `cpus_per_pair` CPUs. Ray retries a task
whose worker process or node dies (`max_retries`); the retry continues the pair from its last
checkpoint where it can read it (`cluster.repro.resume`), else starts it again from scratch
with the same seeds, so its result is the one an uninterrupted run gives, and the collector
replaces the lost attempt's log lines with the checkpoint's. An exception raised by the pair
itself (a bad config, a non-finite loss) is not retried: it ends the run, as it does locally.

With a `store` (`cluster.repro.resume.PairStore`), pairs it records as finished are not run
again: their results come from it, and each new result is recorded as it arrives.

The Ray side (tasks, the event board, shipping the code to the nodes) is
`cluster.repro.fanout_ray`, imported only when an address is given.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import queue
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any

from cluster.repro.pairs import (
    POLL_S,
    Collector,
    FanOutConfig,
    Pair,
    PairEvent,
    PairFn,
    StatusLine,
    run_pair,
)

log = logging.getLogger(__name__)


def run_pairs(
    fn: PairFn,
    pairs: Sequence[Pair],
    args: tuple,
    cfg: FanOutConfig,
    log_dir: Path | None = None,
    on_result: Callable[[Pair, Any], None] | None = None,
    status: StatusLine | None = None,
    store: Any = None,
) -> list:
    """Run `fn(pair.algo, pair.env, *args, report=...)` for every pair where `cfg` says.

    Args:
        fn: a module-level function (it is pickled by reference to reach other processes).
        pairs: the pairs, in the order of the returned results.
        args: the arguments every pair gets after (algo, env).
        cfg: where to run them.
        log_dir: folder for the evaluation logs, None for none.
        on_result: called in the driver with each pair's result as it arrives.
        status: the status line to keep on the terminal, None for none.
        store: finished pairs' results (`cluster.repro.resume.PairStore`): pairs it holds
            are not run (nor handed to `on_result`), new results are recorded in it.

    Returns:
        fn's results, one per pair in `pairs` order.

    Raises ClusterError when the cluster cannot be reached or a pair is lost more than
    `cfg.max_retries` times; an exception of `fn` itself is raised as it is.
    """
    collector = Collector(pairs, log_dir, status)
    results = {}

    def arrived(pair: Pair, result: Any) -> None:
        if store is not None:
            store.record(pair, result)
        if on_result is not None:
            on_result(pair, result)

    try:
        for p in pairs:
            if store is not None and (done := store.finished(p)) is not None:
                results[p] = done
                collector.skip(p)
        todo = [p for p in pairs if p not in results]
        if todo and cfg.address:
            from cluster.repro.fanout_ray import run_ray  # imports ray

            results.update(zip(todo, run_ray(fn, todo, args, cfg, collector, arrived), strict=True))
        elif todo and cfg.workers <= 1:
            for p in todo:
                results[p] = run_pair(fn, p, args, _Direct(collector))
                arrived(p, results[p])
        elif todo:
            results.update(
                zip(todo, _run_pool(fn, todo, args, cfg.workers, collector, arrived), strict=True)
            )
    finally:
        collector.close()
    return [results[p] for p in pairs]


class _Direct:
    """A sink handing events straight to the collector (pairs run in the driver)."""

    def __init__(self, collector: Collector):
        self.collector = collector

    def put(self, event: PairEvent) -> None:
        self.collector.handle(event)
        self.collector.tick()


_pool_events: Any = None  # the event queue of a local pool's worker process


def _pool_init(events: Any, driver: int) -> None:
    from cluster.repro.resume import die_with_parent

    global _pool_events
    _pool_events = events
    die_with_parent(driver)


def _pool_pair(fn: PairFn, pair: Pair, args: tuple) -> Any:
    return run_pair(fn, pair, args, _pool_events)


def _drain_queue(events: Any, collector: Collector, block_s: float = 0.0) -> None:
    """Hand every queued event to the collector, waiting up to `block_s` for each."""
    while True:
        try:
            collector.handle(events.get(timeout=block_s) if block_s else events.get_nowait())
        except queue.Empty:
            collector.tick()
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
    with ProcessPoolExecutor(
        workers, initializer=_pool_init, initargs=(events, os.getpid())
    ) as pool:
        futures = {pool.submit(_pool_pair, fn, p, args): p for p in pairs}
        pending = set(futures)
        while pending:
            ready, pending = wait(pending, timeout=POLL_S, return_when=FIRST_COMPLETED)
            _drain_queue(events, collector)
            for f in ready:
                arrived(futures[f], f.result())  # raises the pair's exception here
    # A worker puts its last events before it returns, but the queue's feeder thread may
    # deliver them after the result: wait for every pair's "finished".
    while not collector.finished.issuperset(pairs):
        before = len(collector.finished)
        _drain_queue(events, collector, block_s=10.0)
        if len(collector.finished) == before:
            log.warning("the local workers' last events did not arrive; logs may be short")
            break
    return [f.result() for f in futures]

"""`credit bench load`: a load generator, one CPU-bound process per core (or `--procs`), to
measure how training and benchmarks slow down on a shared machine.

Each process spins in a pure-Python loop (no I/O, no syscalls) at normal priority, as
`python3 -c "while True: pass"` does. `LoadGenerator` is the same as a context manager (what
`credit bench learn --compare-load` runs its loaded measurement under).
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import time
from pathlib import Path

from cluster.bench.common import emit
from cluster.bench.scaling_stats import parse_proc_stat
from cluster.commands import add_command
from cluster.cpu import usable_cpus
from cluster.errors import UsageError

GRACE_S = 10.0


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "load",
        "Keep CPUs busy: one CPU-bound process per usable core (or --procs) for --seconds, "
        "then print the load average and each process's CPU seconds as JSON.",
    )
    p.add_argument("--procs", type=int, default=0, help="busy processes (0: one per usable CPU)")
    p.add_argument("--seconds", type=float, default=60.0, help="how long to keep them busy")
    p.add_argument("--out", help="also write the JSON here")
    p.set_defaults(func=cmd_load)


def _spin(stop_at: float) -> None:
    """Busy until the monotonic clock passes `stop_at` (read every million iterations)."""
    while time.monotonic() < stop_at:
        for _ in range(1_000_000):
            pass


class LoadGenerator:
    """`procs` busy processes while the `with` block runs (each stops by itself `seconds`
    after the start, plus a grace of GRACE_S, should this process die without stopping it).

    Calling loop::

        with LoadGenerator(procs=2, seconds=600) as load:
            ...measure...
        load.cpu_s          # CPU seconds each process got
    """

    def __init__(self, procs: int = 0, seconds: float = 3600.0):
        self.procs, self.seconds = procs or usable_cpus(), seconds
        self.workers: list = []
        self.cpu_s: list[float] = []

    def __enter__(self) -> LoadGenerator:
        ctx = multiprocessing.get_context("spawn")  # no copy of this process's torch state
        # CLOCK_MONOTONIC is one clock for every process of a Linux machine
        stop_at = time.monotonic() + self.seconds + GRACE_S
        self.workers = [ctx.Process(target=_spin, args=(stop_at,)) for _ in range(self.procs)]
        for w in self.workers:
            w.daemon = True
            w.start()
        deadline = time.monotonic() + 30.0  # until each one spins (a spawn imports first)
        while time.monotonic() < deadline and min(map(_cpu_seconds, self.pids)) < 0.1:
            time.sleep(0.05)
        return self

    @property
    def pids(self) -> list[int | None]:
        return [w.pid for w in self.workers]

    def __exit__(self, *exc: object) -> None:
        self.cpu_s = [_cpu_seconds(pid) for pid in self.pids]
        for w in self.workers:
            w.terminate()
        for w in self.workers:
            w.join(timeout=10)


def _cpu_seconds(pid: int | None) -> float:
    """User + system CPU seconds of a live process (/proc/<pid>/stat); 0 if unreadable."""
    try:
        _, ticks = parse_proc_stat(Path(f"/proc/{pid}/stat").read_text())
        return round(ticks / os.sysconf("SC_CLK_TCK"), 2)
    except (OSError, ValueError, IndexError):
        return 0.0


def cmd_load(args: argparse.Namespace) -> int:
    if args.procs < 0:
        raise UsageError(f"--procs must be >= 0 (0: one per usable CPU), got {args.procs}")
    if args.seconds <= 0:
        raise UsageError(f"--seconds must be > 0, got {args.seconds}")
    before = os.getloadavg()
    load = LoadGenerator(args.procs, args.seconds)
    with load:
        time.sleep(args.seconds)
        after = os.getloadavg()
    figures = {
        "procs": load.procs,
        "seconds": args.seconds,
        "usable_cpus": usable_cpus(),
        "load_avg_before": [round(x, 2) for x in before],
        "load_avg_after": [round(x, 2) for x in after],
        "cpu_s": load.cpu_s,
    }
    emit("load", figures, args.out)
    return 0

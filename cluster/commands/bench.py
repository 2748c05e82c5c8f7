"""`credit bench <what>`: benchmarks that print one JSON object (machine, command, figures).

Each benchmark lives in `cluster/bench/<what>.py` and exposes `register(subparsers)`; the
list below is the whole registry of benchmarks.
"""

from __future__ import annotations

import argparse

from cluster.bench import codec as codec_bench
from cluster.bench import env as env_bench
from cluster.bench import learn as learn_bench
from cluster.bench import load as load_bench
from cluster.bench import matrix as matrix_bench
from cluster.bench import memory as memory_bench
from cluster.bench import open_loop as open_loop_bench
from cluster.bench import scaling as scaling_bench
from cluster.bench import service as service_bench
from cluster.bench import train as train_bench
from cluster.bench import update as update_bench
from cluster.commands import add_command

BENCHES: list = [
    env_bench,
    codec_bench,
    service_bench,
    matrix_bench,
    scaling_bench,
    learn_bench,
    train_bench,
    load_bench,
    update_bench,
    memory_bench,
    open_loop_bench,
]


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "bench",
        "Run a benchmark; each prints one JSON object (machine, command, figures) and "
        "writes a file only where it says so.",
    )
    bench_sub = p.add_subparsers(dest="bench_command", required=True, metavar="BENCH")
    for module in BENCHES:
        module.register(bench_sub)

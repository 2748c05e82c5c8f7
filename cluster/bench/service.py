"""`credit bench service`: buffer service inserts/s and sample latency over loopback.

Starts `credit buffer serve` as a subprocess (fresh snapshot dir, fsync policy as given)
and drives it from 1 and 4 client threads, each with its own BufferClient: first every
client inserts `--inserts` episodes one per request (as actors do), then every client
issues `--samples` sample requests of `--batch` episodes from the replay table. Before
the clock starts, one episode is packed and decoded in the bench's process, so that loading
the compiled packing kernels (numba's cache; compiled on a machine's first run) is not
counted as the service's time.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from buffer_service.client import BufferClient
from buffer_service.episode import Episode, EpisodeBatch, EpisodeSchema
from buffer_service.packed import PackedEpisode
from cluster.bench.common import emit, synthetic_episode
from cluster.commands import add_command

SIZES = {
    "3m": EpisodeSchema(n_agents=3, obs_dim=30, state_dim=48, n_actions=9, max_t=60),
    "bane_vs_bane": EpisodeSchema(n_agents=24, obs_dim=336, state_dim=984, n_actions=30, max_t=200),
}


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "service",
        "Measure the buffer service's inserts per second and sample latency and print "
        "JSON; --out also writes it.",
    )
    p.add_argument("--env-size", choices=sorted(SIZES), default="3m", help="episode sizes")
    p.add_argument("--clients", type=int, nargs="+", default=[1, 4], help="client counts")
    p.add_argument("--inserts", type=int, default=300, help="insert requests per client")
    p.add_argument("--samples", type=int, default=100, help="sample requests per client")
    p.add_argument("--batch", type=int, default=32, help="episodes per sample")
    p.add_argument("--no-fsync", action="store_true", help="serve with --no-fsync")
    p.add_argument("--out", help="also write the JSON here")
    p.set_defaults(func=cmd_service)


def start_server(workdir: str, fsync: bool, capacity: int) -> tuple[subprocess.Popen, int]:
    port_file = Path(workdir) / "port.json"
    cmd = [sys.executable, "-m", "cluster.cli", "buffer", "serve", "--port", "0",
           "--port-file", str(port_file), "--snapshot-dir", str(Path(workdir) / "snap"),
           "--snapshot-every", "0",
           "--table", f"name=replay,kind=replay,capacity={capacity}"]  # fmt: skip
    if not fsync:
        cmd.append("--no-fsync")
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 30
    while not port_file.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise RuntimeError("credit buffer serve did not start")
        time.sleep(0.02)
    return proc, json.loads(port_file.read_text())["port"]


def _parallel(n: int, fn) -> float:
    threads = [threading.Thread(target=fn, args=(i,)) for i in range(n)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return time.perf_counter() - t0


def run_clients(args: argparse.Namespace, n_clients: int) -> dict:
    schema = SIZES[args.env_size]
    rng = np.random.default_rng(0)
    pool = [synthetic_episode(schema, schema.max_t, 0, rng, i) for i in range(16)]
    EpisodeBatch.from_episodes([PackedEpisode.pack(pool[0])])  # load the kernels, untimed
    with tempfile.TemporaryDirectory() as work:
        proc, port = start_server(work, not args.no_fsync, n_clients * args.inserts)
        try:
            clients = [BufferClient(port=port, schema=schema) for _ in range(n_clients)]

            def insert(i: int) -> None:
                for seq in range(args.inserts):
                    ep = pool[seq % len(pool)]
                    clients[i].insert(
                        [Episode(**{**ep.__dict__, "actor_id": i, "episode_seq": seq})]
                    )

            insert_s = _parallel(n_clients, insert)
            lat: list[list[float]] = [[] for _ in range(n_clients)]

            def sample(i: int) -> None:
                for _ in range(args.samples):
                    t0 = time.perf_counter()
                    clients[i].sample("replay", args.batch)
                    lat[i].append(time.perf_counter() - t0)

            sample_s = _parallel(n_clients, sample)
            st = clients[0].stats()
            stored = st["episodes_stored"]
            for c in clients:
                c.close()
        finally:
            proc.terminate()
            proc.wait(30)
    all_lat = np.array([x for xs in lat for x in xs]) * 1e3
    n_ins = n_clients * args.inserts
    return {
        "clients": n_clients,
        "episodes_stored": stored,
        "inserts_per_s": round(n_ins / insert_s, 1),
        # fsyncs that acknowledged the inserts (group commit: fewer than inserts)
        "log_fsyncs": st.get("log_fsyncs"),
        "sample_p50_ms": round(float(np.percentile(all_lat, 50)), 3),
        "sample_p99_ms": round(float(np.percentile(all_lat, 99)), 3),
        "samples_per_s": round(n_clients * args.samples / sample_s, 1),
        "sampled_episodes_per_s": round(n_clients * args.samples * args.batch / sample_s, 1),
    }


def cmd_service(args: argparse.Namespace) -> int:
    schema = SIZES[args.env_size]
    runs = [run_clients(args, n) for n in args.clients]
    figures = {
        "env_size": args.env_size,
        "schema": schema.to_dict(),
        "fsync": not args.no_fsync,
        "inserts_per_client": args.inserts,
        "samples_per_client": args.samples,
        "batch": args.batch,
        "cpus_available": os.cpu_count(),
        "runs": runs,
    }
    if len(runs) >= 2:
        figures["insert_scaling"] = round(runs[-1]["inserts_per_s"] / runs[0]["inserts_per_s"], 3)
    emit("service", figures, out=args.out)
    return 0

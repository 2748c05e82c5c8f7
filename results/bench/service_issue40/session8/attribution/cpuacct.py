"""CPU seconds per insert, client process and server process, for the tree on PYTHONPATH."""

import json
import os
import sys
import tempfile
import time

import numpy as np

from buffer_service.client import BufferClient
from buffer_service.episode import Episode
from cluster.bench import service as S


def proc_cpu(pid):
    with open(f"/proc/{pid}/stat") as fh:
        f = fh.read().split(")")[1].split()
    return np.array([int(f[11]), int(f[12])]) / os.sysconf("SC_CLK_TCK")


def proc_ctx(pid):
    d = {}
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if "ctxt_switches" in line:
                k, v = line.split(":")
                d[k.strip()] = int(v)
    return d


def run(n_clients, inserts, fsync):
    schema = S.SIZES["3m"]
    rng = np.random.default_rng(0)
    pool = [S.synthetic_episode(schema, schema.max_t, 0, rng, i) for i in range(16)]
    try:
        from buffer_service.episode import EpisodeBatch
        from buffer_service.packed import PackedEpisode

        EpisodeBatch.from_episodes([PackedEpisode.pack(pool[0])])
    except ImportError:
        pass
    with tempfile.TemporaryDirectory() as work:
        proc, port = S.start_server(work, fsync, n_clients * inserts)
        clients = [BufferClient(port=port, schema=schema) for _ in range(n_clients)]
        for c in clients:  # warm: one insert each
            c.insert(
                [
                    Episode(
                        **{**pool[0].__dict__, "actor_id": 100 + clients.index(c), "episode_seq": 0}
                    )
                ]
            )
        s0, c0, x0, t0 = proc_cpu(proc.pid), os.times(), proc_ctx(proc.pid), time.perf_counter()

        def ins(i):
            for seq in range(inserts):
                ep = pool[seq % 16]
                clients[i].insert([Episode(**{**ep.__dict__, "actor_id": i, "episode_seq": seq})])

        S._parallel(n_clients, ins)
        t1, c1, s1, x1 = time.perf_counter(), os.times(), proc_cpu(proc.pid), proc_ctx(proc.pid)
        for c in clients:
            c.close()
        proc.terminate()
        proc.wait(30)
    n = n_clients * inserts
    return {
        "clients": n_clients,
        "wall_us_per_insert": round((t1 - t0) / n * 1e6, 1),
        "client_cpu_us": round(((c1.user - c0.user) + (c1.system - c0.system)) / n * 1e6, 1),
        "client_user_us": round((c1.user - c0.user) / n * 1e6, 1),
        "server_cpu_us": round(float((s1 - s0).sum()) / n * 1e6, 1),
        "server_sys_us": round(float((s1 - s0)[1]) / n * 1e6, 1),
        "server_vol_ctx_per_insert": round(
            (x1["voluntary_ctxt_switches"] - x0["voluntary_ctxt_switches"]) / n, 2
        ),
        "server_invol_ctx_per_insert": round(
            (x1["nonvoluntary_ctxt_switches"] - x0["nonvoluntary_ctxt_switches"]) / n, 2
        ),
    }


if __name__ == "__main__":
    fsync = "--no-fsync" not in sys.argv
    print(
        json.dumps(
            {"tag": sys.argv[1], "fsync": fsync, "runs": [run(1, 1000, fsync), run(4, 500, fsync)]}
        )
    )

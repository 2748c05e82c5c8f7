"""Start `credit buffer serve` under cProfile (profserve.py), insert N episodes from 4 clients,
and stop it: the server's profile lands in TAG.prof. Usage: profrun.py TAG N."""

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from buffer_service.client import BufferClient
from buffer_service.episode import Episode
from cluster.bench import service as S

tag, n = sys.argv[1], int(sys.argv[2])
schema = S.SIZES["3m"]
rng = np.random.default_rng(0)
pool = [S.synthetic_episode(schema, schema.max_t, 0, rng, i) for i in range(16)]
with tempfile.TemporaryDirectory() as work:
    port_file = Path(work) / "port.json"
    cmd = [
        sys.executable,
        str(Path(__file__).with_name("profserve.py")),
        "buffer",
        "serve",
        "--port",
        "0",
        "--port-file",
        str(port_file),
        "--snapshot-dir",
        str(Path(work) / "snap"),
        "--snapshot-every",
        "0",
        "--no-fsync",
        "--table",
        f"name=replay,kind=replay,capacity={4 * n + 10}",
    ]
    proc = subprocess.Popen(cmd, env={**os.environ, "PROF_OUT": f"{tag}.prof"})
    while not port_file.exists():
        time.sleep(0.05)
    port = json.loads(port_file.read_text())["port"]
    clients = [BufferClient(port=port, schema=schema) for _ in range(4)]

    def ins(i):
        for seq in range(n):
            clients[i].insert(
                [Episode(**{**pool[seq % 16].__dict__, "actor_id": i, "episode_seq": seq})]
            )

    S._parallel(4, ins)
    proc.terminate()
    proc.wait(30)

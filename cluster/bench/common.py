"""What every benchmark's JSON carries (the machine and the command that made it), and the
synthetic episodes the buffer benchmarks insert."""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from buffer_service.episode import Episode, EpisodeSchema

# CPU features that change what a benchmark measures: the vector width of the float32
# kernels and whether bfloat16 products run natively (`learner.precision`)
CPU_FLAGS = ("avx2", "avx512f", "avx512_bf16", "amx_bf16", "amx_tile")
OPENMP_ENV = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "OMP_NUM_THREADS")


def cpu_info(cpuinfo: Path = Path("/proc/cpuinfo")) -> dict[str, Any]:
    """The CPU's model name and which of `CPU_FLAGS` it has; sessions do not always get the
    same machine, so every benchmark records which CPU made it."""
    from learner.precision import cpu_model_and_flags  # imports torch: only when asked

    model, flags = cpu_model_and_flags(cpuinfo)
    return {"cpu_model": model or "unknown", "cpu_flags": [f for f in CPU_FLAGS if f in flags]}


def machine() -> dict[str, Any]:
    info: dict[str, Any] = {
        "hostname": platform.node(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        **cpu_info(),
        "numpy": np.__version__,
        # how torch's OpenMP threads wait (read once as torch loads; `cluster.cpu`)
        "openmp_env": {k: os.environ.get(k) for k in OPENMP_ENV},
    }
    try:
        import torch

        info["torch"] = torch.__version__
        info["torch_threads"] = torch.get_num_threads()
    except ImportError:
        pass
    return info


def emit(name: str, figures: dict[str, Any], out: str | None = None) -> dict[str, Any]:
    """Print (and optionally write) one JSON object for benchmark `name`."""
    record = {
        "benchmark": name,
        "command": " ".join(["credit", *sys.argv[1:]]) if sys.argv else "",
        "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": machine(),
        **figures,
    }
    text = json.dumps(record, indent=2)
    print(text)
    if out:
        with open(out, "w") as f:
            f.write(text + "\n")
    return record


def synthetic_episode(
    schema: EpisodeSchema, length: int, actor_id: int, rng, episode_seq: int = 0
) -> Episode:
    """A random episode of `length` transitions with the arrays and dtypes of `schema`."""
    t, n = length, schema.n_agents
    return Episode(
        obs=rng.random((t + 1, n, schema.obs_dim), dtype=np.float32),
        state=rng.random((t + 1, schema.state_dim), dtype=np.float32),
        avail_actions=np.ones((t + 1, n, schema.n_actions), np.uint8),
        actions=rng.integers(0, schema.n_actions, (t, n)),
        reward=rng.random(t, dtype=np.float32),
        terminated=np.eye(1, t, t - 1, dtype=bool)[0],
        filled=np.ones(t, bool),
        actor_id=actor_id,
        episode_seq=episode_seq,
    )

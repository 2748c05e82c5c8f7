"""A local multi-process Ray cluster kept on loopback: start, inspect, stop, connect.

Ray binds the machine's external address unless told otherwise, and Ray 2.60 turns token
authentication on for `ray start`. Every Ray process we start and every driver we connect
therefore gets the same environment (`ray_environment()`): the node address 127.0.0.1,
`RAY_AUTH_MODE=token` and a token file created once, readable by this user only.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from cluster.metrics import default_state_dir

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"


class ClusterError(RuntimeError):
    """The Ray cluster could not be started, reached or stopped."""


def state_dir() -> Path:
    return default_state_dir() / "cluster"


def token_path() -> Path:
    """The cluster's auth token file, created (mode 0600) on first use."""
    path = state_dir() / "ray_auth_token"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_hex(32))
    return path


def ray_environment() -> dict[str, str]:
    """Variables every Ray process and driver of ours needs (see the module docstring)."""
    return {
        "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0",
        "RAY_AUTH_MODE": "token",
        "RAY_AUTH_TOKEN_PATH": str(token_path()),
        "RAY_USAGE_STATS_ENABLED": "0",
    }


def apply_ray_environment() -> None:
    """Set `ray_environment()` in this process before `import ray` connects anywhere; values
    the user already set (e.g. RAY_AUTH_TOKEN_PATH for a remote cluster) are kept."""
    user_token = "RAY_AUTH_TOKEN" in os.environ or "RAY_AUTH_TOKEN_PATH" in os.environ
    for key, value in ray_environment().items():
        if key == "RAY_AUTH_TOKEN_PATH" and user_token:
            continue
        os.environ.setdefault(key, value)


@dataclass(frozen=True)
class ClusterState:
    """What `credit cluster up` recorded: where the head listens and with how many CPUs."""

    address: str
    num_cpus: int

    def save(self) -> None:
        path = state_dir() / "state.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"address": self.address, "num_cpus": self.num_cpus}))

    @classmethod
    def load(cls) -> ClusterState | None:
        path = state_dir() / "state.json"
        if not path.exists():
            return None
        d = json.loads(path.read_text())
        return cls(d["address"], int(d["num_cpus"]))


def _ray_cli() -> str:
    exe = Path(sys.executable).with_name("ray")
    if exe.exists():
        return str(exe)
    found = shutil.which("ray")
    if not found:
        raise ClusterError("the `ray` command is not installed (pip install 'ray[default]')")
    return found


def _run_ray(args: list[str], timeout: float = 120.0) -> subprocess.CompletedProcess:
    env = {**os.environ, **ray_environment()}
    return subprocess.run(
        [_ray_cli(), *args], env=env, capture_output=True, text=True, timeout=timeout
    )


def up(num_cpus: int, port: int = 6379, host: str = LOOPBACK) -> ClusterState:
    """Start a Ray head node (it spawns its worker processes) listening on `host`.

    Raises ClusterError if one of ours is already running or `ray start` fails.
    """
    if num_cpus < 1:
        raise ClusterError(f"--num-cpus must be >= 1, got {num_cpus}")
    current = ClusterState.load()
    if current is not None and _alive(current):
        raise ClusterError(
            f"a credit Ray cluster is already up at {current.address}; `credit cluster down` first"
        )
    args = [
        "start",
        "--head",
        "--node-ip-address",
        host,
        "--port",
        str(port),
        "--num-cpus",
        str(num_cpus),
    ]
    args += ["--include-dashboard=false", "--disable-usage-stats"]
    done = _run_ray(args)
    if done.returncode != 0:
        raise ClusterError(
            f"ray start failed (exit {done.returncode}):\n{done.stderr.strip()[-2000:]}"
        )
    state = ClusterState(f"{host}:{port}", num_cpus)
    state.save()
    log.info("Ray head up at %s with %d CPUs", state.address, num_cpus)
    return state


def _alive(state: ClusterState) -> bool:
    return _run_ray(["status", "--address", state.address], timeout=60).returncode == 0


def status() -> str:
    """`ray status` of our cluster, or a line saying none is up."""
    state = ClusterState.load()
    if state is None:
        return "no credit Ray cluster recorded (start one with `credit cluster up`)"
    done = _run_ray(["status", "--address", state.address], timeout=60)
    if done.returncode != 0:
        err = done.stderr.strip()[-1000:]
        return f"the recorded cluster at {state.address} does not answer:\n{err}"
    return f"address: {state.address}\n{done.stdout.strip()}"


def down() -> None:
    """Stop every Ray process of this user on this machine (`ray stop`) and forget the state."""
    done = _run_ray(["stop", "--force"])
    if done.returncode != 0:
        raise ClusterError(
            f"ray stop failed (exit {done.returncode}): {done.stderr.strip()[-1000:]}"
        )
    (state_dir() / "state.json").unlink(missing_ok=True)


def connect(address: str | None, num_cpus: int) -> str:
    """Connect this driver to `address` ("auto" = the recorded cluster, else Ray's own
    discovery), or with no address start a private local Ray instance on loopback for the
    lifetime of this process. Returns a description."""
    apply_ray_environment()
    import ray

    if address == "auto":
        # The cluster `credit cluster up` recorded, else Ray's own discovery (RAY_ADDRESS, as
        # KubeRay and `ray up` set it, or a head started on this machine with `ray start`).
        state = ClusterState.load()
        address = state.address if state is not None else "auto"
    if address:
        ray.init(address=address, logging_level="WARNING", log_to_driver=True)
        return f"joined Ray cluster at {address}"
    ray.init(
        num_cpus=num_cpus,
        include_dashboard=False,
        logging_level="WARNING",
        _node_ip_address=LOOPBACK,
    )
    return f"started a local Ray instance with {num_cpus} CPUs on {LOOPBACK}"

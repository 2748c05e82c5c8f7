"""A local multi-process Ray cluster kept on loopback: start, inspect, stop, connect.

Ray binds the machine's external address unless told otherwise, and Ray 2.60 turns token
authentication on for `ray start`. Every Ray process we start and every driver we connect
therefore gets the same environment (`ray_environment()`): the node address 127.0.0.1,
`RAY_AUTH_MODE=token` and a token file created once, readable by this user only.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

from cluster.errors import Terminated
from cluster.metrics.discovery import default_state_dir

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"


class ClusterError(RuntimeError):
    """The Ray cluster could not be started, reached or stopped."""


class UnreachableClusterError(ClusterError):
    """No Ray cluster answers at the address a command was given."""


def state_dir() -> Path:
    return default_state_dir() / "cluster"


def token_path() -> Path:
    """The cluster's auth token file, created (mode 0600) on first use.

    Several of our processes may create it at once (two runs started together with a fresh
    state folder): the token is written whole to a file of this process's own and linked into
    place, so nobody reads a half-written token and whoever links second keeps the first's."""
    path = state_dir() / "ray_auth_token"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_hex(32))
        try:
            os.link(tmp, path)  # atomic, and never replaces a token that is already there
        except FileExistsError:
            pass
        finally:
            tmp.unlink()
    return path


def start_lock_path() -> Path:
    """The file every private Ray start of this machine locks (see `local_start_lock`)."""
    import tempfile

    return Path(tempfile.gettempdir()) / "credit-ray-local-start.lock"


@contextlib.contextmanager
def local_start_lock(timeout_s: float = 300.0):
    """Hold a machine-wide lock while a private Ray instance starts.

    Ray chooses its ports (GCS, raylet, workers) by probing for free ones before its processes
    bind them, so two instances started at the same moment can pick the same port and one
    fails ("Failed to start GCS"; ray-project/ray#53906). Our runs start one at a time: when
    `ray.init` returns every port of the instance is bound. The lock is an flock on a file in
    the temporary folder, released when the holder exits, even by kill -9. If it cannot be
    taken (another user's file, or `timeout_s` passes) the start goes ahead unserialised,
    with a warning."""
    import fcntl

    path = start_lock_path()
    try:
        f = open(path, "a")  # noqa: SIM115 - closed below, which releases the lock
    except OSError as e:
        log.warning("starting Ray without the start lock (%s: %s)", path, e)
        yield
        return
    with f:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    log.warning(
                        "another Ray start held %s for %.0f s; starting anyway", path, timeout_s
                    )
                    break
                time.sleep(0.1)
        yield


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
    """What `credit cluster up` recorded: where the head listens, with how many CPUs, and the
    process group `ray start` ran in (every head process is in it; `down` stops that group)."""

    address: str
    num_cpus: int
    pgid: int | None = None

    def save(self) -> None:
        path = state_dir() / "state.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        d = {"address": self.address, "num_cpus": self.num_cpus, "pgid": self.pgid}
        path.write_text(json.dumps(d))

    @classmethod
    def load(cls) -> ClusterState | None:
        path = state_dir() / "state.json"
        if not path.exists():
            return None
        d = json.loads(path.read_text())
        return cls(d["address"], int(d["num_cpus"]), d.get("pgid"))


def _ray_cli() -> str:
    exe = Path(sys.executable).with_name("ray")
    if exe.exists():
        return str(exe)
    found = shutil.which("ray")
    if not found:
        raise ClusterError("the `ray` command is not installed (pip install 'ray[default]')")
    return found


def _run_ray(
    args: list[str], timeout: float = 120.0, new_session: bool = False
) -> tuple[subprocess.CompletedProcess, int]:
    """Run the `ray` CLI; returns its result and its pid (its process group's id when
    `new_session`: the processes it leaves running stay in that group)."""
    env = {**os.environ, **ray_environment()}
    with subprocess.Popen(
        [_ray_cli(), *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=new_session,
    ) as proc:
        try:
            out, err = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise ClusterError(f"`ray {args[0]}` did not finish in {timeout:.0f} s") from None
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err), proc.pid


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
    with local_start_lock():  # `ray start` chooses its other ports as ray.init does
        done, pgid = _run_ray(args, new_session=True)
    if done.returncode != 0:
        raise ClusterError(
            f"ray start failed (exit {done.returncode}):\n{done.stderr.strip()[-2000:]}"
        )
    state = ClusterState(f"{host}:{port}", num_cpus, pgid)
    state.save()
    _wait_ready(state.address)
    log.info("Ray head up at %s with %d CPUs", state.address, num_cpus)
    return state


def _wait_ready(address: str, timeout_s: float = 60.0) -> None:
    """Wait until `ray status` reports the head's resources: right after `ray start` it
    answers "No cluster status" for a few seconds."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        done = _ray_status(address)
        if done.returncode == 0 and "No cluster status" not in done.stdout:
            return
        time.sleep(1.0)
    log.warning("Ray head at %s does not report its status after %.0f s", address, timeout_s)


def _ray_status(address: str) -> subprocess.CompletedProcess:
    return _run_ray(["status", "--address", address], timeout=60)[0]


def _alive(state: ClusterState) -> bool:
    return _ray_status(state.address).returncode == 0


def status() -> str:
    """`ray status` of our cluster, or a line saying none is up."""
    state = ClusterState.load()
    if state is None:
        return "no credit Ray cluster recorded (start one with `credit cluster up`)"
    done = _ray_status(state.address)
    if done.returncode != 0:
        err = done.stderr.strip()[-1000:]
        return f"the recorded cluster at {state.address} does not answer:\n{err}"
    return f"address: {state.address}\n{done.stdout.strip()}"


class Proc(NamedTuple):
    """One process, from /proc/<pid>/stat and cmdline."""

    ppid: int
    pgid: int
    sid: int
    state: str  # "R", "S", ..., "Z" for a zombie
    cmd: str


def process_table() -> dict[int, Proc]:
    """pid -> `Proc` of every process we can read (Linux /proc)."""
    table = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:  # exited meanwhile, or not ours to read
            continue
        f = stat[stat.rindex(")") + 2 :].split()
        table[int(entry.name)] = Proc(int(f[1]), int(f[2]), int(f[3]), f[0], cmdline.strip())
    return table


def with_descendants(table: dict[int, Proc], roots: set[int]) -> set[int]:
    """`roots` and every process of `table` below them."""
    found = set(roots)
    while children := {pid for pid, p in table.items() if p.ppid in found} - found:
        found |= children
    return found


def cluster_processes(pgid: int) -> list[int]:
    """The head's processes: the members of `ray start`'s process group that are Ray's (a
    reused group id names no Ray process), and their descendants (workers set up groups of
    their own, but their parent is the raylet)."""
    table = process_table()
    ray = {pid for pid, p in table.items() if p.pgid == pgid and "ray" in p.cmd.lower()}
    return sorted(with_descendants(table, ray))


def _signal(pids: list[int], sig: int) -> None:
    for pid in pids:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, sig)


def _forget_ray_address(address: str) -> None:
    """Remove Ray's "latest cluster" file if it names `address` (as `ray stop` does), so no
    driver tries to join the stopped head."""
    from ray._common.utils import get_ray_address_file  # no connection: safe before the env

    path = Path(get_ray_address_file(None))
    with contextlib.suppress(OSError):
        if path.read_text().strip() == address:
            path.unlink()


def down(grace_s: float = 10.0) -> int:
    """Stop the cluster `up` started, and only it: SIGTERM to its processes, SIGKILL to those
    still there after `grace_s`. Other Ray instances on the machine (other users' or other
    runs' private ones) are left alone. Returns how many processes were signalled.

    Raises ClusterError for a state file from before process groups were recorded.
    """
    state = ClusterState.load()
    if state is None:
        return 0
    if state.pgid is None:
        raise ClusterError(
            f"{state_dir() / 'state.json'} records no process group (written by an older "
            "credit); stop that cluster with `ray stop`, then delete the file"
        )
    pids = cluster_processes(state.pgid)
    _signal(pids, signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline and set(pids) & set(process_table()):
        time.sleep(0.2)
    _signal(sorted(set(pids) & set(process_table())), signal.SIGKILL)
    _forget_ray_address(state.address)
    (state_dir() / "state.json").unlink(missing_ok=True)
    log.info("stopped %d Ray processes of the cluster at %s", len(pids), state.address)
    return len(pids)


def check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """Raise ClusterError unless something accepts TCP connections at `address` ("host:port",
    optionally "ray://host:port"). `ray.init` on an address nobody listens at retries for
    minutes and logs a warning every few seconds; this answers at once, with what to do."""
    hostport = address.removeprefix("ray://")
    host, sep, port = hostport.rpartition(":")
    if not sep or not port.isdigit():
        raise UnreachableClusterError(
            f"--address takes 'auto' or HOST:PORT of a Ray head, got {address!r}"
        )
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as e:
        raise UnreachableClusterError(
            f"no Ray cluster answers at {address} ({e.strerror or e}); start one with "
            "`credit cluster up --num-cpus N` (then use --address auto), or pass "
            "--address HOST:PORT of a running Ray head (`ray start --head` prints it)"
        ) from None


def _raise_terminated(signum, frame) -> None:
    raise Terminated()


def _terminate_like_interrupt() -> None:
    """After `ray.init` started a private instance: SIGTERM to this process raises
    `Terminated` (a KeyboardInterrupt), so that it stops as after Ctrl-C, its `finally`
    blocks and `ray.shutdown` included. `ray.init` leaves a C++ handler that prints a stack
    and ends the process at once, and a driver ended so leaves the raylet's dashboard and
    runtime-env agents running, orphaned. Only from the main thread (signal handlers can be
    set nowhere else)."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _raise_terminated)


def connect(address: str | None, num_cpus: int, runtime_env: dict | None = None) -> str:
    """Connect this driver to `address` ("auto" = the recorded cluster, else Ray's own
    discovery; or "host:port"), or with no address start a private local Ray instance on
    loopback for the lifetime of this process. Returns a description.

    Args:
        address: None, "auto" or "host:port" of a Ray head (GCS port).
        num_cpus: CPUs of the private instance (ignored when joining a cluster).
        runtime_env: Ray runtime environment of this job (e.g. `py_modules` to ship code to
            every node).

    Raises UnreachableClusterError when `address` names no reachable cluster.
    """
    apply_ray_environment()
    import ray

    if address == "auto":
        # The cluster `credit cluster up` recorded, else Ray's own discovery (RAY_ADDRESS, as
        # KubeRay and `ray up` set it, or a head started on this machine with `ray start`).
        state = ClusterState.load()
        address = state.address if state is not None else "auto"
        if state is not None:
            try:
                check_reachable(address)
            except UnreachableClusterError as e:
                raise UnreachableClusterError(
                    f"--address auto: the cluster recorded in {state_dir() / 'state.json'} is "
                    f"gone: {e}"
                ) from None
    elif address:
        check_reachable(address)
    if address:
        try:
            ray.init(
                address=address,
                logging_level="WARNING",
                log_to_driver=True,
                runtime_env=runtime_env,
            )
        except ConnectionError as e:  # "auto" found no running instance
            raise UnreachableClusterError(
                f"no Ray cluster found for --address {address}: {e} Start one with "
                "`credit cluster up --num-cpus N`, or pass --address HOST:PORT"
            ) from None
        return f"joined Ray cluster at {address}"
    with local_start_lock():
        ray.init(
            address="local",  # always a new instance, never the latest `ray start` head
            num_cpus=num_cpus,
            include_dashboard=False,
            logging_level="WARNING",
            runtime_env=runtime_env,
            _node_ip_address=LOOPBACK,
        )
    _terminate_like_interrupt()
    return f"started a local Ray instance with {num_cpus} CPUs on {LOOPBACK}"

"""Run the real `prometheus` binary on loopback, scraping every live credit run on the machine
(each run's own file-SD file, linked into `cluster.metrics.discovery.runs_sd_dir()`), or one file-SD
file or glob.

`credit metrics up` calls `start`, `credit metrics down` calls `stop`. The server runs detached
(its own session) so it outlives the command; its pid, port and URL are kept in
`<state_dir>/prometheus.json`. `query` and `query_range` read its HTTP API (tests and the
dashboard use them).

    cfg = PrometheusConfig(port=9090)   # sd_file "": every live run (~/.credit/metrics/runs/*.json)
    state = start(cfg)              # waits for /-/ready
    query(state.url, "sum(rate(credit_env_steps_total[10s]))")
    stop(cfg.state_dir)
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import time
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from cluster.config.schema import ConfigError
from cluster.metrics.discovery import default_state_dir, pid_alive, prune_run_sd, runs_sd_glob

log = logging.getLogger(__name__)

INSTALL_HINT = (
    "the `prometheus` binary is not on PATH; install it with `apt-get install prometheus` "
    "(Debian/Ubuntu) or put the release binary from https://prometheus.io/download/ on PATH"
)
STATE_FILE = "prometheus.json"


@dataclass(frozen=True)
class PrometheusConfig:
    """How to run the local Prometheus.

    Attributes:
        sd_file: what to scrape: a file_sd JSON file listing exporters (created empty when
            missing), or a glob of such files (`*` in the last path element, as Prometheus
            allows); "" = every live run on this machine, `<state>/metrics/runs/*.json`
            (each cluster run links its OUT/targets.json there while it runs).
        port: HTTP port on 127.0.0.1; 0 picks a free one.
        host: address to bind; loopback unless you mean to expose it.
        scrape_interval_s: seconds between scrapes of each target (1-2 s suits live charts).
        retention: how long samples are kept (Prometheus duration, e.g. "1d").
        data_dir: TSDB folder; "" = `<state_dir>/data`.
        state_dir: where the generated config, log and pid file go; "" = `~/.credit/metrics`.
        binary: the executable to run (looked up on PATH).
        ready_timeout_s: how long to wait for /-/ready.
    """

    sd_file: str = ""
    port: int = 9090
    host: str = "127.0.0.1"
    scrape_interval_s: float = 1.0
    retention: str = "1d"
    data_dir: str = ""
    state_dir: str = ""
    binary: str = "prometheus"
    ready_timeout_s: float = 60.0

    def validate(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ConfigError(f"prometheus port must be in 0..65535, got {self.port}")
        if not 0.1 <= self.scrape_interval_s <= 300:
            raise ConfigError(
                f"scrape_interval_s must be in [0.1, 300], got {self.scrape_interval_s}"
            )
        if self.ready_timeout_s <= 0:
            raise ConfigError(f"ready_timeout_s must be > 0, got {self.ready_timeout_s}")

    def resolved(self) -> PrometheusConfig:
        """A copy with every "" path filled in with its default and made absolute."""
        state = Path(self.state_dir or default_state_dir() / "metrics").expanduser().resolve()
        return dataclasses.replace(
            self,
            state_dir=str(state),
            sd_file=(
                str(Path(self.sd_file).expanduser().absolute()) if self.sd_file else runs_sd_glob()
            ),
            data_dir=str(Path(self.data_dir or state / "data").expanduser().resolve()),
        )


@dataclass(frozen=True)
class PrometheusState:
    """A running Prometheus: what `start` records and `stop` reads."""

    pid: int
    port: int
    url: str
    config_file: str
    log_file: str


def find_binary(name: str = "prometheus") -> str:
    """Absolute path of the Prometheus executable; ConfigError with the install hint if absent."""
    path = shutil.which(name)
    if path is None:
        raise ConfigError(
            INSTALL_HINT if name == "prometheus" else f"{name!r} not found; {INSTALL_HINT}"
        )
    return path


def render_config(cfg: PrometheusConfig) -> str:
    """The prometheus.yml that scrapes every target of `cfg.sd_file` (paths must be resolved)."""
    interval = f"{int(cfg.scrape_interval_s * 1000)}ms"
    timeout = f"{max(100, int(cfg.scrape_interval_s * 800))}ms"
    doc = {
        "global": {"scrape_interval": interval, "evaluation_interval": interval},
        "scrape_configs": [
            {
                "job_name": "credit",
                "scrape_interval": interval,
                "scrape_timeout": timeout,
                "metrics_path": "/metrics",
                "file_sd_configs": [{"files": [cfg.sd_file], "refresh_interval": "2s"}],
            }
        ],
    }
    return "# Generated by `credit metrics up`; edits are overwritten.\n" + yaml.safe_dump(
        doc, sort_keys=False
    )


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago (Prometheus itself cannot bind port 0)."""
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def read_state(state_dir: str | Path) -> PrometheusState | None:
    """The recorded Prometheus of `state_dir`, or None if none is recorded."""
    path = Path(state_dir) / STATE_FILE
    try:
        return PrometheusState(**json.loads(path.read_text()))
    except FileNotFoundError:
        return None
    except (ValueError, TypeError) as e:
        raise ConfigError(
            f"{path} is corrupt ({e}); delete it and run `credit metrics up`"
        ) from None


def _is_prometheus(pid: int) -> bool:
    # Guard against a recycled pid: only signal a process whose command is prometheus.
    try:
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[0]
    except OSError:
        return pid_alive(pid)
    return b"prometheus" in os.path.basename(cmd)


def wait_ready(url: str, proc: subprocess.Popen | None, timeout_s: float, log_file: str) -> None:
    """Poll `url`/-/ready until it answers 200; RuntimeError naming the log if it never does."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(
                f"prometheus exited with code {proc.returncode}; last log lines:\n{_tail(log_file)}"
            )
        try:
            with urllib.request.urlopen(f"{url}/-/ready", timeout=2) as r:
                if r.status == 200:
                    return
        except (urllib.error.URLError, OSError):
            pass
        time.sleep(0.2)
    raise RuntimeError(
        f"prometheus not ready after {timeout_s:.0f}s; see {log_file}:\n{_tail(log_file)}"
    )


def _tail(path: str, lines: int = 15) -> str:
    try:
        return "\n".join(Path(path).read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no log)"


def start(cfg: PrometheusConfig) -> PrometheusState:
    """Start Prometheus detached and wait until it is ready.

    Args:
        cfg: the settings; "" paths take their defaults.

    Returns:
        The recorded state (pid, port, URL, config and log paths).

    Raises:
        ConfigError: no binary, or one is already running for this state dir.
        RuntimeError: it exited or never became ready (the message carries its log tail).
    """
    cfg.validate()
    cfg = cfg.resolved()
    binary = find_binary(cfg.binary)
    state_dir = Path(cfg.state_dir)
    old = read_state(state_dir)
    if old is not None and pid_alive(old.pid) and _is_prometheus(old.pid):
        raise ConfigError(
            f"prometheus already running (pid {old.pid}, {old.url}); `credit metrics down` first"
        )
    state_dir.mkdir(parents=True, exist_ok=True)
    Path(cfg.data_dir).mkdir(parents=True, exist_ok=True)
    sd = Path(cfg.sd_file)
    if "*" in sd.name:  # a glob: its folder must exist for Prometheus to watch it
        sd.parent.mkdir(parents=True, exist_ok=True)
        prune_run_sd()
    elif not sd.exists():
        sd.parent.mkdir(parents=True, exist_ok=True)
        sd.write_text("[]\n")
    config_file = state_dir / "prometheus.yml"
    config_file.write_text(render_config(cfg))
    port = cfg.port or free_port(cfg.host)
    log_file = state_dir / "prometheus.log"
    argv = [
        binary,
        f"--config.file={config_file}",
        f"--storage.tsdb.path={cfg.data_dir}",
        f"--storage.tsdb.retention.time={cfg.retention}",
        f"--web.listen-address={cfg.host}:{port}",
        "--web.enable-lifecycle",
    ]
    log.info("starting %s", " ".join(argv))
    with open(log_file, "ab") as out:
        proc = subprocess.Popen(
            argv,
            stdout=out,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )
    url = f"http://{cfg.host}:{port}"
    state = PrometheusState(proc.pid, port, url, str(config_file), str(log_file))
    (state_dir / STATE_FILE).write_text(json.dumps(dataclasses.asdict(state), indent=2) + "\n")
    try:
        wait_ready(url, proc, cfg.ready_timeout_s, str(log_file))
    except RuntimeError:
        _terminate(proc.pid)
        (state_dir / STATE_FILE).unlink(missing_ok=True)
        raise
    return state


def _gone(pid: int) -> bool:
    """Whether `pid` has exited; reaps it when it is this process's child (a zombie child
    still answers os.kill, so `credit metrics down` in the process that started Prometheus,
    as in the tests, must reap it)."""
    try:
        return os.waitpid(pid, os.WNOHANG)[0] == pid
    except ChildProcessError:  # not our child: its parent reaps it
        return not pid_alive(pid)


def _wait_gone(pid: int, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not _gone(pid):
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.1)
    return True


def _terminate(pid: int, grace_s: float = 10.0) -> None:
    """SIGTERM, then SIGKILL after `grace_s`; returns once the process is gone (and reaped
    when it is our child)."""
    try:
        os.kill(pid, signal.SIGTERM)
    except ProcessLookupError:
        return
    if _wait_gone(pid, grace_s):
        return
    log.warning("prometheus (pid %d) ignored SIGTERM for %.0fs; killing it", pid, grace_s)
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        return
    if not _wait_gone(pid, 10.0):
        log.warning("prometheus (pid %d) still there 10 s after SIGKILL", pid)


def stop(state_dir: str | Path = "") -> PrometheusState | None:
    """Stop the Prometheus recorded in `state_dir` ("" = default). Returns what was stopped."""
    state_dir = Path(state_dir or default_state_dir() / "metrics")
    state = read_state(state_dir)
    if state is None:
        return None
    if pid_alive(state.pid) and _is_prometheus(state.pid):
        _terminate(state.pid)
    else:
        log.info("prometheus pid %d is not running any more", state.pid)
    (state_dir / STATE_FILE).unlink(missing_ok=True)
    return state


def running_url(state_dir: str | Path = "") -> str | None:
    """URL of the Prometheus recorded in `state_dir` if it is alive, else None."""
    try:
        state = read_state(Path(state_dir or default_state_dir() / "metrics"))
    except ConfigError:
        return None
    if state is None or not pid_alive(state.pid):
        return None
    return state.url


def _api(prom_url: str, path: str, params: dict[str, Any], timeout_s: float) -> Any:
    url = f"{prom_url.rstrip('/')}{path}?{urllib.parse.urlencode(params)}"
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as r:
            body = json.loads(r.read())
    except urllib.error.HTTPError as e:
        body = json.loads(e.read() or b"{}")
        raise ValueError(
            f"prometheus rejected {params.get('query')!r}: {body.get('error', e)}"
        ) from None
    if body.get("status") != "success":
        raise ValueError(f"prometheus query failed: {body.get('error', body)}")
    return body["data"]["result"]


def query(prom_url: str, promql: str, timeout_s: float = 10.0) -> list[dict]:
    """Instant query through Prometheus's HTTP API.

    Args:
        prom_url: e.g. "http://127.0.0.1:9090".
        promql: the expression.

    Returns:
        The result vector: [{"metric": {label: value}, "value": [unix_time, "text value"]}, ...]
    """
    return _api(prom_url, "/api/v1/query", {"query": promql}, timeout_s)


def query_range(
    prom_url: str, promql: str, start: float, end: float, step_s: float, timeout_s: float = 10.0
) -> list[dict]:
    """Range query: [{"metric": {...}, "values": [[unix_time, "text value"], ...]}, ...]."""
    params = {"query": promql, "start": f"{start:.3f}", "end": f"{end:.3f}", "step": f"{step_s:g}"}
    return _api(prom_url, "/api/v1/query_range", params, timeout_s)

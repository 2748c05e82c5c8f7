"""Prometheus metrics of the actors and the learner (DESIGN.md §5), defined once, here.

Every component owns its own `CollectorRegistry`, so several exporters (one per actor, one for
the learner) can live in one process, as they do in `--mode local` and in tests. Everything is
recorded per episode batch or per update, never per environment step, and no label carries a
per-step value. The buffer's `credit_buffer_*` metrics live in `buffer_service/metrics.py`.

The calling loop::

    actor = ActorMetrics(actor_id=3)
    host, port = serve(actor.registry)              # 127.0.0.1, a free port
    while running:
        episodes = worker.collect(4)
        actor.record(len(episodes), sum(int(e.filled.sum()) for e in episodes))

    learner = LearnerMetrics()
    serve(learner.registry, port=0)
    learner.record_update(seconds, {"critic": 0.3, "actor": -0.1}, weights_version=12)
    learner.record_policy_lag([12 - e.policy_version for e in batch_episodes])

The launcher lists every endpoint in a Prometheus file-service-discovery file with
`write_file_sd`; `credit metrics up` and `credit dashboard` read it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import sys
import tempfile
import threading
from collections.abc import Iterable, Mapping
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
)

log = logging.getLogger(__name__)

#: Loopback only unless a caller asks otherwise (DESIGN.md §4: bind 127.0.0.1 by default).
DEFAULT_HOST = "127.0.0.1"

#: Seconds per learner update: from a millisecond (tiny nets) to a minute (huge batches).
# fmt: off
UPDATE_SECONDS_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5,
                          1.0, 2.5, 5.0, 10.0, 30.0, 60.0)
# fmt: on
#: Versions between the policy that acted and the learner's current one.
POLICY_LAG_BUCKETS = (0, 1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 64, 128)

#: Every name a scrape of an actor or learner exporter can show (counters with `_total`).
ACTOR_METRIC_NAMES = (
    "credit_env_steps_total",
    "credit_episodes_total",
    "credit_weights_version",
)
LEARNER_METRIC_NAMES = (
    "credit_learner_updates_total",
    "credit_learner_update_seconds",
    "credit_policy_lag_versions",
    "credit_weights_version",
    "credit_loss",
    "credit_test_return",
    "credit_test_win_rate",
    "credit_kl_masked_fraction",
    "credit_actor_restarts_total",
)
#: The buffer service's names (defined in `buffer_service/metrics.py`, listed for the dashboards).
BUFFER_METRIC_NAMES = (
    "credit_buffer_inserts_total",
    "credit_buffer_samples_total",
    "credit_buffer_size_episodes",
    "credit_buffer_rejected_total",
)

_LABEL_NAME = re.compile(r"^[a-zA-Z_][a-zA-Z0-9_]*$")


def _counter_name(name: str) -> str:
    # prometheus-client appends `_total` itself; give it the stem so the exposed name is exact.
    return name.removesuffix("_total")


class ActorMetrics:
    """The metrics of one rollout actor, in a registry of its own.

    Args:
        actor_id: the actor's id; becomes the `actor` label (one value per actor, bounded).
        registry: registry to register in; a fresh one when None.
    """

    def __init__(self, actor_id: int | str, registry: CollectorRegistry | None = None) -> None:
        self.actor_id = str(actor_id)
        self.registry = registry if registry is not None else CollectorRegistry()
        self._env_steps = Counter(
            _counter_name("credit_env_steps_total"),
            "Environment steps taken by this actor (summed per episode).",
            ["actor"],
            registry=self.registry,
        ).labels(actor=self.actor_id)
        self._episodes = Counter(
            _counter_name("credit_episodes_total"),
            "Episodes completed by this actor.",
            ["actor"],
            registry=self.registry,
        ).labels(actor=self.actor_id)
        self._version = Gauge(
            "credit_weights_version",
            "Version of the policy weights this component holds.",
            ["component"],
            registry=self.registry,
        ).labels(component=f"actor-{self.actor_id}")

    def record(self, episodes: int, env_steps: int) -> None:
        """Count a batch of finished episodes.

        Args:
            episodes: how many episodes finished (>= 0).
            env_steps: their environment steps, padding excluded (>= 0).
        """
        if episodes < 0 or env_steps < 0:
            raise ValueError(f"episodes and env_steps must be >= 0, got {episodes}, {env_steps}")
        self._episodes.inc(episodes)
        self._env_steps.inc(env_steps)

    def set_weights_version(self, version: int) -> None:
        """Record the weights version the actor now acts with."""
        self._version.set(version)


class LearnerMetrics:
    """The learner's metrics (and the launcher's actor-restart count), in one registry.

    Args:
        registry: registry to register in; a fresh one when None.
    """

    def __init__(self, registry: CollectorRegistry | None = None) -> None:
        r = self.registry = registry if registry is not None else CollectorRegistry()
        self._updates = Counter(
            _counter_name("credit_learner_updates_total"), "Learner updates done.", registry=r
        )
        self._update_seconds = Histogram(
            "credit_learner_update_seconds",
            "Wall time of one learner update, in seconds.",
            buckets=UPDATE_SECONDS_BUCKETS,
            registry=r,
        )
        self._lag = Histogram(
            "credit_policy_lag_versions",
            "Learner version minus the version that acted, per trained episode.",
            buckets=POLICY_LAG_BUCKETS,
            registry=r,
        )
        self._version = Gauge(
            "credit_weights_version",
            "Version of the policy weights this component holds.",
            ["component"],
            registry=r,
        ).labels(component="learner")
        self._loss = Gauge("credit_loss", "Last value of each loss term.", ["name"], registry=r)
        self._test_return = Gauge(
            "credit_test_return", "Mean return of the last greedy test episodes.", registry=r
        )
        self._win_rate = Gauge(
            "credit_test_win_rate", "Win rate (0-1) of the last greedy test episodes.", registry=r
        )
        self._kl_masked = Gauge(
            "credit_kl_masked_fraction",
            "Fraction (0-1) of timesteps whose advantage the EM-CAC KL mask zeroed.",
            registry=r,
        )
        self._restarts = Counter(
            _counter_name("credit_actor_restarts_total"),
            "Rollout actors restarted after a failure.",
            registry=r,
        )

    def record_update(
        self, seconds: float, losses: Mapping[str, float], weights_version: int
    ) -> None:
        """Record one learner update.

        Args:
            seconds: wall time of the update.
            losses: loss term name -> value (a handful of fixed names, e.g. "critic", "actor").
            weights_version: version of the weights after the update.
        """
        if seconds < 0:
            raise ValueError(f"update seconds must be >= 0, got {seconds}")
        self._updates.inc()
        self._update_seconds.observe(seconds)
        for name, value in losses.items():
            self._loss.labels(name=name).set(float(value))
        self._version.set(weights_version)

    def record_policy_lag(self, lags: Iterable[int]) -> None:
        """Record the policy lag (in versions) of each episode of a trained batch."""
        for lag in lags:
            self._lag.observe(max(0, int(lag)))

    def record_test(self, return_mean: float, win_rate: float | None = None) -> None:
        """Record a test (greedy evaluation) result.

        Args:
            return_mean: mean episode return.
            win_rate: fraction of won episodes in [0, 1]; None where the env has no winner.
        """
        self._test_return.set(float(return_mean))
        if win_rate is not None:
            if not 0.0 <= win_rate <= 1.0:
                raise ValueError(f"win_rate must be in [0, 1], got {win_rate}")
            self._win_rate.set(float(win_rate))

    def set_kl_masked_fraction(self, fraction: float) -> None:
        """Record the fraction of timesteps the KL mask zeroed in the last update (EM-CAC)."""
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f"KL-masked fraction must be in [0, 1], got {fraction}")
        self._kl_masked.set(float(fraction))

    def actor_restarted(self, count: int = 1) -> None:
        """Count rollout-actor restarts (called by whoever restarts them)."""
        self._restarts.inc(count)


def exposed_names(registry: CollectorRegistry) -> set[str]:
    """The metric names a scrape of `registry` shows (histograms by their base name).

    Returns:
        e.g. {"credit_env_steps_total", "credit_learner_update_seconds", ...}
    """
    names: set[str] = set()
    for family in registry.collect():
        names.add(f"{family.name}_total" if family.type == "counter" else family.name)
    return names


# ---------------------------------------------------------------- exporter


class QuietHTTPServer(ThreadingHTTPServer):
    """A threading HTTP server for which a client that hangs up before the reply is no error.

    The dashboard gives up on a scrape after 2 s and a browser drops a poll when its page
    reloads; a busy process then answers into a closed socket. socketserver would print a
    BrokenPipeError traceback for each; this logs one debug line instead.
    """

    def handle_error(self, request: object, client_address: tuple) -> None:
        if isinstance(sys.exc_info()[1], (BrokenPipeError, ConnectionResetError)):
            log.debug("http %s:%s hung up before the reply", *client_address[:2])
            return
        super().handle_error(request, client_address)


class _Handler(BaseHTTPRequestHandler):
    registry: CollectorRegistry  # set on the per-server subclass

    def do_GET(self) -> None:
        if self.path.split("?")[0] not in ("/", "/metrics"):
            self.send_error(404, "only /metrics is served")
            return
        body = generate_latest(self.registry)
        self.send_response(200)
        self.send_header("Content-Type", CONTENT_TYPE_LATEST)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: object) -> None:
        log.debug("exporter %s: " + format, self.address_string(), *args)


_SERVERS: dict[tuple[str, int], ThreadingHTTPServer] = {}
_SERVERS_LOCK = threading.Lock()


def serve(registry: CollectorRegistry, port: int = 0, host: str = DEFAULT_HOST) -> tuple[str, int]:
    """Serve `registry` at http://host:port/metrics from a daemon thread.

    Args:
        registry: what to expose.
        port: TCP port; 0 picks a free one.
        host: address to bind; loopback by default. Bind a routable address only on a
            multi-node cluster whose Prometheus scrapes over the network.

    Returns:
        (host, port) actually bound; pass it to `stop` to close the exporter.
    """
    if not 0 <= port <= 65535:
        raise ValueError(f"port must be in 0..65535, got {port}")
    handler = type("MetricsHandler", (_Handler,), {"registry": registry})
    server = QuietHTTPServer((host, port), handler)
    server.daemon_threads = True
    bound = (host, int(server.server_address[1]))
    thread = threading.Thread(target=server.serve_forever, name=f"metrics-{bound[1]}", daemon=True)
    thread.start()
    with _SERVERS_LOCK:
        _SERVERS[bound] = server
    log.info("metrics exporter on http://%s:%d/metrics", *bound)
    return bound


def stop(endpoint: tuple[str, int]) -> None:
    """Close an exporter that `serve` started in this process (no-op when unknown)."""
    with _SERVERS_LOCK:
        server = _SERVERS.pop(tuple(endpoint), None)  # type: ignore[arg-type]
    if server is not None:
        server.shutdown()
        server.server_close()


# ---------------------------------------------------------------- file service discovery


def default_state_dir() -> Path:
    """Where `credit` keeps run-time state: $CREDIT_STATE_DIR, else ~/.credit."""
    return Path(os.environ.get("CREDIT_STATE_DIR") or Path.home() / ".credit")


def runs_sd_dir() -> Path:
    """Where every live cluster run on this machine links its own file-SD file (one
    `<run folder name>-<hash>.json` link per run, pointing at the run's OUT/targets.json);
    `credit metrics up` and `credit dashboard` read every file in it."""
    return default_state_dir() / "metrics" / "runs"


def runs_sd_glob() -> str:
    """The file_sd glob over `runs_sd_dir()` that Prometheus is given."""
    return str(runs_sd_dir() / "*.json")


def register_run_sd(targets_file: str | Path) -> Path:
    """Link a run's own file-SD file into `runs_sd_dir()`, so that whatever scrapes "every
    live run" finds it; prunes the links of runs that are gone first. The same file always
    gets the same link (replaced atomically).

    Returns:
        The link.
    """
    target = Path(targets_file).resolve()
    prune_run_sd()
    digest = hashlib.sha1(str(target).encode()).hexdigest()[:12]
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", target.parent.name) or "run"
    link = runs_sd_dir() / f"{name}-{digest}.json"
    link.parent.mkdir(parents=True, exist_ok=True)
    tmp = link.with_name(f".{link.name}.tmp")  # not matched by the *.json glob
    tmp.unlink(missing_ok=True)
    tmp.symlink_to(target)
    os.replace(tmp, link)
    return link


def unregister_run_sd(link: str | Path) -> None:
    """Remove a run's link (the run has ended); its own targets file stays."""
    Path(link).unlink(missing_ok=True)


def _run_alive(targets_file: Path) -> bool:
    """Whether the run that wrote `targets_file` still runs: its folder's cluster.json names
    a learner pid that is alive (a run without cluster.json yet counts as alive)."""
    if not targets_file.exists():
        return False
    try:
        pid = int(json.loads((targets_file.parent / "cluster.json").read_text())["learner"]["pid"])
    except FileNotFoundError:
        return True
    except (ValueError, KeyError, TypeError):
        return False
    return pid_alive(pid)


def pid_alive(pid: int) -> bool:
    """Whether process `pid` exists and is not a zombie (an exited child never reaped)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except (OSError, IndexError):
        return True


def prune_run_sd() -> list[Path]:
    """Remove the links of runs that are gone (killed, or their folder deleted); returns them."""
    folder = runs_sd_dir()
    removed = []
    for link in sorted(folder.glob("*.json")) if folder.is_dir() else []:
        if not _run_alive(link.resolve()):
            link.unlink(missing_ok=True)
            removed.append(link)
            log.info("dropped the file-SD link of a run that is gone: %s", link)
    return removed


def read_runs_sd() -> list[tuple[str, int]]:
    """Every (host, port) of every live run's file-SD file (a run's broken file is skipped
    with a warning, so one bad run does not hide the others)."""
    folder = runs_sd_dir()
    out: list[tuple[str, int]] = []
    for link in sorted(folder.glob("*.json")) if folder.is_dir() else []:
        try:
            out += read_file_sd(link)
        except ValueError as e:
            log.warning("skipping %s: %s", link, e)
    return out


def write_file_sd(
    path: str | Path,
    targets: Iterable[tuple[str, int]],
    labels: Mapping[str, str] | None = None,
) -> Path:
    """Write a Prometheus file_sd JSON file listing `targets`, atomically.

    Prometheus re-reads the file when it changes; a reader never sees a half-written file
    because the content goes to a temporary file in the same folder that then replaces `path`.

    Args:
        path: the file to (re)write; parent folders are created.
        targets: (host, port) of every exporter.
        labels: labels Prometheus attaches to every target (e.g. {"job": "credit"}).

    Returns:
        The path written.
    """
    labels = dict(labels or {})
    for key, value in labels.items():
        if not _LABEL_NAME.match(key) or key.startswith("__"):
            raise ValueError(f"invalid Prometheus label name {key!r}")
        if not isinstance(value, str):
            raise ValueError(f"label {key!r} must be a string, got {value!r}")
    entries = []
    for host, port in targets:
        if not host or not 0 < int(port) <= 65535:
            raise ValueError(f"bad target {host!r}:{port!r}")
        entries.append(f"{host}:{int(port)}")
    groups = [{"targets": entries, "labels": labels}] if entries else []
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(groups, f, indent=2)
            f.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def read_file_sd(path: str | Path) -> list[tuple[str, int]]:
    """Every (host, port) listed in a file_sd JSON file; [] when the file does not exist.

    Raises:
        ValueError: the file is not file_sd JSON (the message names the file).
    """
    path = Path(path)
    try:
        groups = json.loads(path.read_text())
    except FileNotFoundError:
        return []
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not JSON ({e})") from None
    if not isinstance(groups, list):
        raise ValueError(f"{path}: file_sd must be a JSON list of target groups")
    out: list[tuple[str, int]] = []
    for group in groups:
        for target in group.get("targets", []) if isinstance(group, dict) else []:
            out.append(parse_target(target))
    return out


def parse_target(text: str) -> tuple[str, int]:
    """`"127.0.0.1:9100"` -> ("127.0.0.1", 9100); ValueError naming the text otherwise."""
    host, sep, port = str(text).strip().rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) <= 65535:
        raise ValueError(f"target must be host:port, got {text!r}")
    return host, int(port)

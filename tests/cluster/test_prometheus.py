"""cluster.metrics.prometheus and `credit metrics up/down`: the generated config, the missing-binary
message, and a real Prometheus scraping real exporters (skipped when it is not installed)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys

import pytest
import yaml

from cluster.cli import main
from cluster.metrics import discovery
from cluster.metrics import prometheus as prom
from tests.cluster.polling import wait_for

HAVE_PROMETHEUS = shutil.which("prometheus") is not None
needs_prometheus = pytest.mark.skipif(
    not HAVE_PROMETHEUS, reason="`prometheus` not on PATH (apt-get install prometheus)"
)


def test_render_config_scrapes_the_sd_file(tmp_path):
    cfg = prom.PrometheusConfig(sd_file=str(tmp_path / "t.json"), state_dir=str(tmp_path))
    doc = yaml.safe_load(prom.render_config(cfg.resolved()))
    (job,) = doc["scrape_configs"]
    assert job["file_sd_configs"][0]["files"] == [str(tmp_path / "t.json")]
    assert job["scrape_interval"] == "1000ms"
    assert doc["global"]["scrape_interval"] == "1000ms"


@pytest.mark.parametrize(
    ("field", "value"), [("port", 70000), ("scrape_interval_s", 0.0), ("ready_timeout_s", 0.0)]
)
def test_bad_config_is_refused(field, value):
    from cluster.config.schema import ConfigError, build

    with pytest.raises(ConfigError, match=field if field != "port" else "port"):
        build(prom.PrometheusConfig, {field: value})


def test_missing_binary_says_how_to_install(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PATH", str(tmp_path))  # an empty PATH: no prometheus on it
    rc = main(["metrics", "up", "--state-dir", str(tmp_path), "--port", "0"])
    assert rc == 2
    assert "apt-get install prometheus" in capsys.readouterr().err


def test_down_without_up_is_harmless(tmp_path, capsys):
    assert main(["metrics", "down", "--state-dir", str(tmp_path)]) == 0
    assert "nothing to stop" in capsys.readouterr().out
    assert main(["metrics", "status", "--state-dir", str(tmp_path)]) == 1


def env_steps_by_actor(url: str) -> dict[str, float]:
    return {
        r["metric"]["actor"]: float(r["value"][1])
        for r in prom.query(url, "credit_env_steps_total")
    }


@needs_prometheus
@pytest.mark.default_tier(reason="watches the default tier's live cluster run")
def test_real_prometheus_scrapes_a_cluster_training(running_training, tmp_path, capsys):
    """`credit metrics up` scrapes a live `credit train --mode cluster`: every actor's env-step
    counter rises, and the learner's update counter and the buffer's size are there."""
    sd = tmp_path / "targets.json"
    state_dir = tmp_path / "state"
    discovery.write_file_sd(
        sd, [discovery.parse_target(t) for t in running_training], {"cluster": "test"}
    )
    args = ["metrics", "up", "--sd-file", str(sd), "--port", "0", "--state-dir", str(state_dir)]
    assert main(args) == 0
    try:
        state = prom.read_state(state_dir)
        assert state is not None and state.url.startswith("http://127.0.0.1:")
        assert state.url in capsys.readouterr().out
        first = wait_for(
            lambda: (s := env_steps_by_actor(state.url)) and len(s) == 2 and s,
            what="both actors in prometheus",
        )
        wait_for(
            lambda: all(v > first[a] for a, v in env_steps_by_actor(state.url).items()),
            what="credit_env_steps_total to increase for every actor",
        )
        updates = wait_for(
            lambda: [
                r
                for r in prom.query(state.url, "credit_learner_updates_total")
                if float(r["value"][1]) > 0
            ],
            what="learner updates in prometheus",
        )
        assert updates[0]["metric"]["cluster"] == "test"  # file_sd labels arrive
        sizes = prom.query(state.url, "credit_buffer_size_episodes")
        assert {r["metric"]["table"] for r in sizes} == {"replay"}
        assert main(["metrics", "up", "--state-dir", str(state_dir), "--port", "0"]) == 2
    finally:
        assert main(["metrics", "down", "--state-dir", str(state_dir)]) == 0
    assert prom.read_state(state_dir) is None
    with pytest.raises(ProcessLookupError):
        os.kill(state.pid, 0)


@needs_prometheus
def test_query_reports_a_bad_expression(tmp_path):
    state = prom.start(
        prom.PrometheusConfig(port=0, state_dir=str(tmp_path), sd_file=str(tmp_path / "sd.json"))
    )
    try:
        with pytest.raises(ValueError, match="rate"):
            prom.query(state.url, "rate(")
        assert prom.query(state.url, "credit_env_steps_total") == []
    finally:
        prom.stop(tmp_path)


@pytest.mark.parametrize("ignores_sigterm", [False, True])
def test_terminate_returns_only_once_the_child_is_gone_and_reaped(ignores_sigterm):
    # `credit metrics down` in the process that started Prometheus (as in the tests above):
    # a child that has exited but is not reaped still answers os.kill(pid, 0).
    code = "import signal, time\n"
    if ignores_sigterm:
        code += "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
    code += "print('ready', flush=True)\ntime.sleep(60)\n"
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "ready"
        prom._terminate(child.pid, grace_s=0.5)
        with pytest.raises(ProcessLookupError):
            os.kill(child.pid, 0)
    finally:
        if child.returncode is None and discovery.pid_alive(child.pid):
            child.kill()
        child.stdout.close()


def test_by_default_prometheus_scrapes_every_live_runs_targets(tmp_path, monkeypatch):
    monkeypatch.setenv("CREDIT_STATE_DIR", str(tmp_path / "state"))
    cfg = prom.PrometheusConfig().resolved()
    doc = yaml.safe_load(prom.render_config(cfg))
    (job,) = doc["scrape_configs"]
    assert job["file_sd_configs"][0]["files"] == [str(tmp_path / "state/metrics/runs/*.json")]


class _Targets:
    """What a wait is for, with Prometheus's view of every target (health, last error)
    at the moment a failed wait prints it."""

    def __init__(self, url: str, what: str):
        self.url, self.what = url, what

    def __str__(self) -> str:
        import json
        import urllib.request

        with urllib.request.urlopen(f"{self.url}/api/v1/targets", timeout=10) as r:
            active = json.load(r)["data"]["activeTargets"]
        seen = [(t["scrapeUrl"], t["health"], t["lastError"]) for t in active]
        return f"{self.what}; the targets: {seen}"


@needs_prometheus
@pytest.mark.slow
def test_two_concurrent_cluster_runs_are_both_scraped(tmp_path, capsys):
    """Two `credit train --mode cluster` runs at once on this machine, each with its own
    targets.json under its folder; one `credit metrics up` (no --sd-file) scrapes both, and a
    run that ends cleanly takes its targets away."""
    pytest.importorskip("ray", reason="cluster mode needs ray")
    state_dir = tmp_path / "state"
    env = {**os.environ, "CREDIT_STATE_DIR": str(state_dir), "PYTHONUNBUFFERED": "1"}
    runs = {name: tmp_path / name for name in ("first", "second")}
    procs = {}
    for name, out in runs.items():
        cmd = [sys.executable, "-m", "cluster.cli", "train", "--mode", "cluster", "--actors", "1"]
        cmd += ["--algo", "vdn", "--env", "matrix/two_step", "--t-max", "100000000"]
        cmd += ["--out", str(out), "--set", "run.test_interval=100000"]
        log = open(tmp_path / f"{name}.log", "w")  # noqa: SIM115 - closed with the process
        procs[name] = (subprocess.Popen(cmd, env=env, stdout=log, stderr=log), log)
    metrics_state = tmp_path / "prometheus"
    try:
        for name, out in runs.items():
            wait_for(
                lambda out=out: len(discovery.read_file_sd(out / "targets.json")) == 3,
                timeout_s=240,
                what=f"{name}'s targets.json (learner, actor, buffer service)",
                proc=procs[name][0],
                log=tmp_path / f"{name}.log",
            )
        up = ["metrics", "up", "--port", "0", "--state-dir", str(metrics_state)]
        assert subprocess.run([sys.executable, "-m", "cluster.cli", *up], env=env).returncode == 0
        state = prom.read_state(metrics_state)
        labels = {str(out.resolve()) for out in runs.values()}

        def updating_runs() -> set[str]:
            rows = prom.query(state.url, "credit_learner_updates_total > 0")
            return {r["metric"]["run"] for r in rows}

        wait_for(lambda: updating_runs() == labels, timeout_s=120, what="both runs' learners")
        # Every exporter of both runs answers. Not at one instant: a learner whose updates
        # are scraped says nothing of the run's other targets, whose first scrape may not
        # have come yet (each target has its own offset in the scrape interval), and on a
        # busy machine a scrape can miss its 0.8 s timeout. Within the last minute each
        # target answered at least once.
        answered = 'max_over_time(up{job="credit"}[1m]) == 1'
        scraped = wait_for(
            lambda: (rows := prom.query(state.url, answered)) and len(rows) == 6 and rows,
            timeout_s=60,
            what=_Targets(state.url, "all six exporters to answer a scrape"),
        )
        assert {r["metric"]["run"] for r in scraped} == labels
        first, _ = procs["first"]  # left in procs, so that `finally` ends it if this times out
        first.send_signal(signal.SIGINT)
        assert first.wait(timeout=120) in (0, 130)
        wait_for(
            lambda: (
                {r["metric"]["run"] for r in prom.query(state.url, 'up{job="credit"}')}
                == {str(runs["second"].resolve())}
            ),
            timeout_s=60,
            what="the ended run's targets to leave Prometheus",
        )
    finally:
        for proc, log in procs.values():
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=120)
            except subprocess.TimeoutExpired:
                proc.kill()
            log.close()
        prom.stop(metrics_state)

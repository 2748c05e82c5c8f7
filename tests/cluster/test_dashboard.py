"""The dashboard without a browser: hand-computed series from snapshots, the PromQL text,
the HTTP API over real exporters, and the command's bad-input errors."""

from __future__ import annotations

import json
import math
import shutil
import time
import urllib.request

import numpy as np
import pytest

from cluster.cli import main
from cluster.dashboard import local
from cluster.dashboard.panels import PANELS, Query
from cluster.dashboard.server import (
    DashboardConfig,
    DashboardServer,
    ExporterSource,
    PrometheusSource,
    panels_payload,
)
from cluster.metrics import discovery
from cluster.metrics import exporters as m
from cluster.metrics import http as mhttp
from cluster.metrics import prometheus as prom


def snap(t, **series):
    """Snapshot from name=value or name={labels-tuple: value} keyword arguments."""
    samples = {}
    for name, v in series.items():
        for labels, value in v.items() if isinstance(v, dict) else [((), v)]:
            samples[(name, tuple(sorted(labels)))] = value
    return local.Snapshot(t, samples)


def test_rate_per_label_over_the_window():
    a0, a1 = (("actor", "0"),), (("actor", "1"),)
    snaps = [
        snap(0, credit_env_steps_total={a0: 0, a1: 100}),
        snap(1, credit_env_steps_total={a0: 10, a1: 130}),
        snap(2, credit_env_steps_total={a0: 30, a1: 140}),
    ]
    q = Query("rate", "credit_env_steps_total", ("actor",), "actor {actor}")
    # window 1.5 s: each point compares with the snapshot at most 1.5 s older
    assert local.evaluate(q, snaps, window_s=1.5) == {
        "actor 0": [(1, 10.0), (2, 20.0)],
        "actor 1": [(1, 30.0), (2, 10.0)],
    }
    # window 2 s: the last point compares with t=0
    assert local.evaluate(q, snaps, window_s=2)["actor 0"][-1] == (2, 15.0)


def test_counter_reset_counts_from_zero_and_sum_merges_instances():
    i1 = (("instance", "a"),)
    i2 = (("instance", "b"),)
    snaps = [snap(0, c_total={i1: 50, i2: 5}), snap(2, c_total={i1: 4, i2: 9})]
    got = local.evaluate(Query("rate", "c_total"), snaps, window_s=10)
    assert got == {"c_total": [(2, (4 + 4) / 2)]}


def test_value_aggregation_and_since():
    snaps = [snap(0, g={(("t", "x"),): 1}), snap(5, g={(("t", "x"),): 3, (("t", "y"),): 4})]
    assert local.evaluate(Query("value", "g", agg="max"), snaps, 10, since=1) == {"g": [(5, 4)]}
    assert local.evaluate(Query("value", "g", ("t",), "{t}"), snaps, 10) == {
        "x": [(0, 1), (5, 3)],
        "y": [(5, 4)],
    }


def test_histogram_mean_and_quantile():
    def h(t, b1, b2, inf, total):
        return snap(
            t,
            h_bucket={(("le", "1.0"),): b1, (("le", "2.0"),): b2, (("le", "+Inf"),): inf},
            h_sum=total,
            h_count=inf,
        )

    snaps = [h(0, 0, 0, 0, 0), h(1, 2, 4, 4, 5.0)]
    assert local.evaluate(Query("hist_mean", "h"), snaps, 5) == {"h": [(1, 1.25)]}
    # rank 0.5*4 = 2 falls at the top of bucket (0, 1]: 1.0; rank 3 is half-way in (1, 2]
    assert local.evaluate(Query("hist_quantile", "h", q=0.5), snaps, 5) == {"h": [(1, 1.0)]}
    assert local.evaluate(Query("hist_quantile", "h", q=0.75), snaps, 5) == {"h": [(1, 1.5)]}


@pytest.mark.parametrize(
    ("q", "buckets", "want"),
    [
        (0.5, {1.0: 0, 2.0: 10, math.inf: 10}, 1.5),
        (0.99, {1.0: 5, math.inf: 10}, 1.0),  # in the +Inf bucket: the highest finite bound
        (0.5, {1.0: 0, math.inf: 0}, math.nan),
    ],
)
def test_bucket_quantile_matches_promql_rules(q, buckets, want):
    got = local.bucket_quantile(q, buckets)
    assert (math.isnan(got) and math.isnan(want)) or got == pytest.approx(want)


def test_promql_text():
    assert (
        Query("rate", "x_total", ("actor",)).promql("30s") == "sum by (actor) (rate(x_total[30s]))"
    )
    assert Query("value", "g", agg="max").promql() == "max (g)"
    assert Query("hist_quantile", "h", q=0.95).promql("1m") == (
        "histogram_quantile(0.95, sum by (le) (rate(h_bucket[1m])))"
    )


def test_a_broken_target_is_reported_not_fatal():
    history = local.ScrapeHistory(lambda: ["ok:1", "bad:2"], fetcher=_fake_fetch)
    s = history.scrape_once(now=10.0)
    assert ("up_total", (("instance", "ok:1"),)) in s.samples
    assert "bad:2" in history.errors


def _fake_fetch(target: str) -> str:
    if target.startswith("bad"):
        raise OSError("connection refused")
    return "# TYPE up counter\nup_total 1\n"


@pytest.fixture
def exporters():
    actors = [m.ActorMetrics(i) for i in range(2)]
    learner = m.LearnerMetrics()
    eps = [mhttp.serve(a.registry) for a in actors] + [mhttp.serve(learner.registry)]
    yield actors, learner, [f"{h}:{p}" for h, p in eps]
    for ep in eps:
        mhttp.stop(ep)


def test_exporter_source_serves_panels_over_http(exporters):
    actors, learner, targets = exporters
    cfg = DashboardConfig(port=0, scrape_interval_s=0.05, rate_window_s=5)
    source = ExporterSource(lambda: targets, cfg)
    for k in range(3):  # scrapes driven by hand: no sleeping, no timing
        for a in actors:
            a.record(episodes=1, env_steps=10 * (k + 1))
        learner.record_update(0.01, {"critic": 1.0}, weights_version=k)
        source.history.scrape_once(now=1000.0 + k)
    payload = panels_payload(source, range_s=60, now=1002.0)
    by_id = {p["id"]: p for p in payload["panels"]}
    assert [p["id"] for p in payload["panels"]] == [p.id for p in PANELS]
    env = {s["name"]: s["points"] for s in by_id["env_steps"]["series"]}
    assert env["actor 0"] == [[1001.0, 20.0], [1002.0, 25.0]]  # (10+20+30-10)/2 at t=1002
    assert by_id["losses"]["series"][0]["name"] == "critic"
    assert by_id["buffer_fill"]["series"] == []
    assert payload["errors"] == []

    server = DashboardServer(cfg, source).start()  # the real thread scrapes too now
    try:
        assert server.url.startswith("http://127.0.0.1:")
        with urllib.request.urlopen(server.url + "api/panels?range=60", timeout=5) as r:
            data = json.loads(r.read())
        assert {p["id"] for p in data["panels"]} == set(by_id)
        with urllib.request.urlopen(server.url, timeout=5) as r:
            assert b"credit" in r.read()
        for bad in ("static/../server.py", "nope", "static/local.py"):
            with pytest.raises(urllib.error.HTTPError):
                urllib.request.urlopen(server.url + bad, timeout=5)
    finally:
        server.close()


@pytest.mark.skipif(shutil.which("prometheus") is None, reason="prometheus not on PATH")
def test_every_panel_query_is_valid_promql(exporters, tmp_path):
    targets = exporters[2]
    sd = discovery.write_file_sd(tmp_path / "sd.json", [discovery.parse_target(t) for t in targets])
    state = prom.start(prom.PrometheusConfig(port=0, sd_file=str(sd), state_dir=str(tmp_path)))
    try:
        payload = panels_payload(PrometheusSource(state.url, DashboardConfig()), 60, time.time())
        assert payload["errors"] == []  # Prometheus parsed every expression
    finally:
        prom.stop(tmp_path)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--targets", "nohostport"], "host:port"),
        (["--targets", ","], "at least one"),
        (["--sd-file", "/nonexistent/t.json"], "does not exist"),
        (["--prometheus", "localhost:9090"], "http"),
        (["--port", "70000", "--targets", "127.0.0.1:1"], "port"),
    ],
)
def test_dashboard_command_rejects_bad_input(argv, message, capsys):
    assert main(["dashboard", *argv]) == 2
    assert message in capsys.readouterr().err


def test_broken_sd_file_is_a_usage_error(tmp_path, capsys):
    bad = tmp_path / "t.json"
    bad.write_text("{nope")
    assert main(["dashboard", "--sd-file", str(bad), "--port", "0"]) == 2
    assert "t.json" in capsys.readouterr().err


def test_policy_lag_percentiles_cover_thousands_of_versions():
    learner = m.LearnerMetrics()
    ep = mhttp.serve(learner.registry)
    try:
        source = ExporterSource(lambda: [f"{ep[0]}:{ep[1]}"], DashboardConfig(port=0))
        source.history.scrape_once(now=1000.0)
        lags = list(range(1000, 2001))  # replayed episodes 1000-2000 versions old
        learner.record_policy_lag(lags)
        source.history.scrape_once(now=1001.0)
    finally:
        mhttp.stop(ep)
    panel = next(p for p in PANELS if p.id == "policy_lag")
    got = {s["name"]: s["points"][-1][1] for s in source.series(panel, 990.0, 1002.0)[0]}
    assert got["mean"] == pytest.approx(1500.0)
    # bucket interpolation (1536, 2048] against the exact 95th percentile: within 5%
    assert got["p95"] == pytest.approx(float(np.percentile(lags, 95)), rel=0.05)


@pytest.mark.parametrize("algo, shown", [("qmix", False), ("emcac", True), (None, True)])
def test_panels_follow_the_runs_algorithm(algo, shown):
    learner = m.LearnerMetrics(algo=algo, family="pg" if algo == "emcac" else "value")
    ep = mhttp.serve(learner.registry)
    try:
        source = ExporterSource(lambda: [f"{ep[0]}:{ep[1]}"], DashboardConfig(port=0))
        source.history.scrape_once(now=1000.0)
        payload = panels_payload(source, range_s=60, now=1000.5)
    finally:
        mhttp.stop(ep)
    ids = [p["id"] for p in payload["panels"]]
    assert ("kl_masked" in ids) is shown
    assert ids[:2] == ["test_win_rate", "test_return"]  # the learning panels first
    assert payload["run"]["algos"] == ([algo] if algo else [])


@pytest.mark.parametrize("summary", [True, False])
def test_an_ended_run_is_finished_or_stopped_not_connection_errors(tmp_path, summary):
    learner = m.LearnerMetrics(algo="qmix", family="value")
    ep = mhttp.serve(learner.registry)
    source = ExporterSource(lambda: [f"{ep[0]}:{ep[1]}"], DashboardConfig(port=0), run_dir=tmp_path)
    learner.record_test(12.5, 0.75)
    source.history.scrape_once(now=1000.0)
    assert panels_payload(source, range_s=60, now=1000.5)["run"]["ended"] is None
    if summary:
        final = {"algo": "qmix", "env": "skirmish/3m", "t_env": 5000, "wall_s": 61.0}
        final |= {"final_test_return_mean": 12.5, "final_test_won_mean": 0.75}
        (tmp_path / "summary.json").write_text(json.dumps(final))
    mhttp.stop(ep)  # the run's process is gone: connection refused from now on
    for k in range(1, 4):
        source.history.scrape_once(now=1000.0 + k)
    assert "Connection refused" in str(source.history.errors)
    payload = panels_payload(source, range_s=60, now=5000.0)
    ended = payload["run"]["ended"]
    assert payload["errors"] == []  # the end explains the silence; no banner of errors
    assert ended["state"] == ("finished" if summary else "stopped")
    assert ended["last_seen"] == 1000.0 and payload["end"] == 1001.0  # charts end at the run
    win = next(p for p in payload["panels"] if p["id"] == "test_win_rate")
    assert win["series"][0]["points"] == [[1000.0, 0.75]]
    if summary:
        assert ended["summary"]["final_test_won_mean"] == 0.75
        assert ended["summary"]["t_env"] == 5000

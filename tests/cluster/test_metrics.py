"""cluster.metrics.exporters: exact names, per-component registries, the HTTP exporter, file SD."""

from __future__ import annotations

import json
import os
import shutil
import socket
import struct
import subprocess
import sys
import threading
import urllib.request

import pytest
from prometheus_client import CollectorRegistry, Gauge
from prometheus_client.parser import text_string_to_metric_families

from cluster.metrics import discovery
from cluster.metrics import exporters as m
from cluster.metrics import http as mhttp

DESIGN_ACTOR_LEARNER = {
    "credit_env_steps_total",
    "credit_episodes_total",
    "credit_learner_updates_total",
    "credit_learner_update_seconds",
    "credit_policy_lag_versions",
    "credit_weights_version",
    "credit_loss",
    "credit_test_return",
    "credit_test_win_rate",
    "credit_kl_masked_fraction",
    "credit_actor_restarts_total",
}


def scrape(endpoint: tuple[str, int]) -> dict[tuple[str, tuple], float]:
    """Sample name + sorted labels -> value, from a real HTTP scrape."""
    host, port = endpoint
    assert host == "127.0.0.1"
    with urllib.request.urlopen(f"http://{host}:{port}/metrics", timeout=5) as r:
        text = r.read().decode()
    out = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def test_names_match_design_section_5():
    names = m.exposed_names(m.ActorMetrics(0).registry)
    assert names | m.exposed_names(m.LearnerMetrics().registry) == DESIGN_ACTOR_LEARNER
    # + the run's algorithm, when the launcher names it (the dashboard picks panels by it)
    names |= m.exposed_names(m.LearnerMetrics(algo="qmix", family="value").registry)
    assert names == DESIGN_ACTOR_LEARNER | {"credit_run_info"}
    assert set(m.ACTOR_METRIC_NAMES) | set(m.LEARNER_METRIC_NAMES) | {m.RUN_INFO_NAME} == names


def test_several_exporters_in_one_process_count_separately():
    a0, a1, learner = m.ActorMetrics(0), m.ActorMetrics("1"), m.LearnerMetrics()
    eps = [mhttp.serve(a0.registry), mhttp.serve(a1.registry), mhttp.serve(learner.registry)]
    try:
        assert len({p for _, p in eps}) == 3 and all(p > 0 for _, p in eps)
        a0.record(episodes=2, env_steps=57)
        a0.record(episodes=1, env_steps=3)
        a1.record(episodes=4, env_steps=100)
        a1.set_weights_version(7)
        s0, s1 = scrape(eps[0]), scrape(eps[1])
        assert s0[("credit_env_steps_total", (("actor", "0"),))] == 60
        assert s0[("credit_episodes_total", (("actor", "0"),))] == 3
        assert s1[("credit_env_steps_total", (("actor", "1"),))] == 100
        assert s1[("credit_weights_version", (("component", "actor-1"),))] == 7
        assert ("credit_env_steps_total", (("actor", "1"),)) not in s0
    finally:
        for ep in eps:
            mhttp.stop(ep)


class _SlowCollector:
    """Holds a scrape until the test lets it go (a busy process answering late)."""

    def __init__(self):
        self.entered, self.release = threading.Event(), threading.Event()

    def collect(self):
        self.entered.set()
        self.release.wait(10)
        return []


def test_a_scraper_that_hangs_up_early_is_no_error_and_the_exporter_keeps_serving(capsys):
    # The dashboard gives up on a scrape after 2 s; an actor busy with its envs can answer
    # later, into a closed socket. That used to print a BrokenPipeError traceback per scrape.
    registry = CollectorRegistry()
    Gauge("credit_probe", "probe", registry=registry).set(3)
    slow = _SlowCollector()
    registry.register(slow)
    ep = mhttp.serve(registry)
    try:
        client = socket.create_connection(ep, timeout=5)
        client.sendall(b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n")
        assert slow.entered.wait(5)
        # close with RST (linger 0), so the exporter's writes fail at once
        client.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        client.close()
        registry.unregister(slow)
        slow.release.set()
        assert scrape(ep)[("credit_probe", ())] == 3
    finally:
        mhttp.stop(ep)
    assert "Traceback" not in capsys.readouterr().err


def test_learner_records_updates_lag_tests_and_restarts():
    lm = m.LearnerMetrics()
    ep = mhttp.serve(lm.registry)
    try:
        lm.record_update(0.02, {"critic": 0.5, "actor": -0.25}, weights_version=3)
        lm.record_update(0.04, {"critic": 0.4, "actor": -0.2}, weights_version=4)
        lm.record_policy_lag([0, 1, 1, 5])
        lm.record_test(12.5, win_rate=0.75)
        lm.record_test(13.0)  # no winner in this env: win rate keeps its last value
        lm.set_kl_masked_fraction(0.125)
        lm.actor_restarted()
        s = scrape(ep)
    finally:
        mhttp.stop(ep)
    assert s[("credit_learner_updates_total", ())] == 2
    assert s[("credit_learner_update_seconds_count", ())] == 2
    assert s[("credit_learner_update_seconds_sum", ())] == pytest.approx(0.06)
    assert s[("credit_loss", (("name", "critic"),))] == pytest.approx(0.4)
    assert s[("credit_loss", (("name", "actor"),))] == pytest.approx(-0.2)
    assert s[("credit_weights_version", (("component", "learner"),))] == 4
    assert s[("credit_policy_lag_versions_count", ())] == 4
    assert s[("credit_policy_lag_versions_sum", ())] == 7
    assert s[("credit_policy_lag_versions_bucket", (("le", "1.0"),))] == 3
    assert s[("credit_test_return", ())] == 13.0
    assert s[("credit_test_win_rate", ())] == 0.75
    assert s[("credit_kl_masked_fraction", ())] == 0.125
    assert s[("credit_actor_restarts_total", ())] == 1


def test_no_label_other_than_the_bounded_ones():
    allowed = {"actor", "component", "name", "le"}
    for reg in (m.ActorMetrics(5).registry, m.LearnerMetrics().registry):
        for family in reg.collect():
            for s in family.samples:
                assert set(s.labels) <= allowed, (s.name, s.labels)


@pytest.mark.parametrize(
    "call",
    [
        lambda: m.ActorMetrics(0).record(-1, 3),
        lambda: m.LearnerMetrics().record_update(-0.1, {}, 1),
        lambda: m.LearnerMetrics().record_test(1.0, win_rate=1.5),
        lambda: m.LearnerMetrics().set_kl_masked_fraction(2.0),
        lambda: mhttp.serve(m.CollectorRegistry(), port=70000),
    ],
)
def test_bad_values_are_refused(call):
    with pytest.raises(ValueError):
        call()


def test_file_sd_roundtrip_and_format(tmp_path):
    path = tmp_path / "sd" / "targets.json"
    discovery.write_file_sd(path, [("127.0.0.1", 9101), ("127.0.0.1", 9102)], {"job": "credit"})
    assert json.loads(path.read_text()) == [
        {"targets": ["127.0.0.1:9101", "127.0.0.1:9102"], "labels": {"job": "credit"}}
    ]
    assert discovery.read_file_sd(path) == [("127.0.0.1", 9101), ("127.0.0.1", 9102)]
    discovery.write_file_sd(path, [])  # rewritten in place; no temporary file left behind
    assert json.loads(path.read_text()) == []
    assert [p.name for p in path.parent.iterdir()] == ["targets.json"]
    assert discovery.read_file_sd(tmp_path / "missing.json") == []


@pytest.mark.parametrize(
    ("targets", "labels"),
    [
        ([("127.0.0.1", 0)], None),
        ([("", 80)], None),
        ([("h", 1)], {"__x": "y"}),
        ([("h", 1)], {"a-b": "y"}),
    ],
)
def test_file_sd_refuses_bad_input(tmp_path, targets, labels):
    with pytest.raises(ValueError):
        discovery.write_file_sd(tmp_path / "t.json", targets, labels)


def test_read_file_sd_names_a_broken_file(tmp_path):
    bad = tmp_path / "t.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match=r"t\.json"):
        discovery.read_file_sd(bad)
    with pytest.raises(ValueError, match="host:port"):
        discovery.parse_target("localhost")


def _run_folder(root, name, pid, port):
    """A run folder as a cluster run leaves it: its own targets.json and cluster.json."""
    out = root / name
    discovery.write_file_sd(out / "targets.json", [("127.0.0.1", port)], {"run": name})
    (out / "cluster.json").write_text(json.dumps({"learner": {"pid": pid}}))
    return out


def test_each_run_links_its_own_targets_into_the_machines_runs_folder(tmp_path, monkeypatch):
    monkeypatch.setenv("CREDIT_STATE_DIR", str(tmp_path / "state"))
    a = _run_folder(tmp_path, "a", os.getpid(), 9101)
    b = _run_folder(tmp_path / "elsewhere", "b", os.getpid(), 9102)
    link_a = discovery.register_run_sd(a / "targets.json")
    link_b = discovery.register_run_sd(b / "targets.json")
    assert link_a != link_b and link_a.parent == link_b.parent == discovery.runs_sd_dir()
    assert link_a.resolve() == (a / "targets.json").resolve()  # the run's own file
    assert discovery.register_run_sd(a / "targets.json") == link_a  # one link per run folder
    assert sorted(discovery.read_runs_sd()) == [("127.0.0.1", 9101), ("127.0.0.1", 9102)]
    discovery.write_file_sd(a / "targets.json", [("127.0.0.1", 9201)])  # the run rewrites its file
    assert sorted(discovery.read_runs_sd()) == [("127.0.0.1", 9102), ("127.0.0.1", 9201)]
    discovery.unregister_run_sd(link_a)
    assert discovery.read_runs_sd() == [("127.0.0.1", 9102)]


def test_runs_that_are_gone_are_pruned(tmp_path, monkeypatch):
    monkeypatch.setenv("CREDIT_STATE_DIR", str(tmp_path / "state"))
    links = {
        name: discovery.register_run_sd(
            _run_folder(tmp_path, name, os.getpid(), port) / "targets.json"
        )
        for name, port in (("live", 9101), ("killed", 9102), ("removed", 9103))
    }
    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)  # fmt: skip
    killed = {"learner": {"pid": int(done.stdout)}}  # exited and reaped: no such process
    (tmp_path / "killed" / "cluster.json").write_text(json.dumps(killed))
    shutil.rmtree(tmp_path / "removed")
    assert sorted(discovery.prune_run_sd()) == sorted([links["killed"], links["removed"]])
    assert sorted(discovery.runs_sd_dir().iterdir()) == [links["live"]]
    assert discovery.read_runs_sd() == [("127.0.0.1", 9101)]

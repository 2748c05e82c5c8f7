"""deploy/grafana/credit.json: the dashboard's panels, and only metric names the code exports."""

from __future__ import annotations

import json
import re
from pathlib import Path

from cluster.dashboard import grafana
from cluster.dashboard.panels import PANELS, metric_names
from cluster.metrics import exporters as m

ROOT = Path(__file__).resolve().parents[2]
GRAFANA = ROOT / "deploy" / "grafana" / "credit.json"
BUFFER_METRICS = ROOT / "buffer_service" / "metrics.py"
# The buffer metrics of docs/design.md; used only until buffer_service/metrics.py exists, then its
# source is read instead.
BUFFER_NAMES_FALLBACK = {
    "credit_buffer_inserts_total",
    "credit_buffer_samples_total",
    "credit_buffer_size_episodes",
    "credit_buffer_rejected_total",
}
NAME = re.compile(r"\bcredit_[a-z0-9_]+")
SERIES_SUFFIXES = ("_bucket", "_sum", "_count")


def exported_names() -> set[str]:
    """Names the code exports: the actor/learner registries plus the buffer service's."""
    names = m.exposed_names(m.ActorMetrics(0).registry) | m.exposed_names(
        m.LearnerMetrics().registry
    )
    if BUFFER_METRICS.exists():
        found = set(re.findall(r"[\"'](credit_buffer_[a-z0-9_]+)[\"']", BUFFER_METRICS.read_text()))
        # prometheus-client exposes a counter named with or without `_total` as `..._total`.
        names |= found | {n if n.endswith("_total") else n + "_total" for n in found}
    else:
        names |= BUFFER_NAMES_FALLBACK
    return names


def histogram_names() -> set[str]:
    registries = (m.ActorMetrics(0).registry, m.LearnerMetrics().registry)
    return {f.name for r in registries for f in r.collect() if f.type == "histogram"}


def unknown_names(exprs: list[str], known: set[str]) -> set[str]:
    """Metric names in `exprs` that are not exported (a histogram's series map to its name)."""
    histograms = histogram_names() & known
    bad = set()
    for expr in exprs:
        for name in NAME.findall(expr):
            base = name
            for suffix in SERIES_SUFFIXES:
                if name.endswith(suffix) and name.removesuffix(suffix) in histograms:
                    base = name.removesuffix(suffix)
            if base not in known:
                bad.add(name)
    return bad


def grafana_exprs() -> list[str]:
    doc = json.loads(GRAFANA.read_text())
    return [t["expr"] for p in doc["panels"] for t in p["targets"]]


def test_grafana_references_only_exported_metrics():
    exprs = grafana_exprs()
    assert exprs
    assert unknown_names(exprs, exported_names()) == set()


def test_the_check_does_catch_a_wrong_name():
    known = exported_names()
    assert unknown_names(["sum(rate(credit_env_step_total[1m]))"], known) == {
        "credit_env_step_total"
    }
    assert unknown_names(["credit_env_steps_total_bucket"], known) == {
        "credit_env_steps_total_bucket"
    }
    assert unknown_names(["rate(credit_policy_lag_versions_bucket[1m])"], known) == set()


def test_every_design_metric_has_a_panel():
    used = {n for e in grafana_exprs() for n in NAME.findall(e)}
    bases = {n.removesuffix(s) for n in used for s in SERIES_SUFFIXES if n.endswith(s)} | used
    missing = (
        set(m.ACTOR_METRIC_NAMES) | set(m.LEARNER_METRIC_NAMES) | BUFFER_NAMES_FALLBACK
    ) - bases
    assert missing == set()
    assert metric_names() <= exported_names()


def test_committed_file_is_the_generated_one():
    # Regenerate with: python -m cluster.dashboard.grafana > deploy/grafana/credit.json
    assert GRAFANA.read_text() == grafana.render()


def test_grafana_panels_mirror_the_live_dashboard():
    doc = json.loads(GRAFANA.read_text())
    assert doc["uid"] and doc["title"] and doc["schemaVersion"] >= 30
    assert [p["title"] for p in doc["panels"]] == [f"{p.title} ({p.unit})" for p in PANELS]
    assert len({p["id"] for p in doc["panels"]}) == len(doc["panels"])
    cells = {(p["gridPos"]["x"], p["gridPos"]["y"]) for p in doc["panels"]}
    assert len(cells) == len(doc["panels"])  # no two panels on top of each other
    for p in doc["panels"]:
        assert p["type"] == "timeseries" and p["targets"]
        assert p["datasource"]["uid"] == "${datasource}"
        assert all(t["expr"] and t["refId"] for t in p["targets"])
    (var,) = doc["templating"]["list"]
    assert var["type"] == "datasource" and var["query"] == "prometheus"

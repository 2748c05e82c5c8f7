"""What the dashboard (and the Grafana dashboard) shows: panels of typed queries.

Each `Query` is both a PromQL expression (for Prometheus and Grafana) and a recipe the
exporter-scraping mode evaluates itself (`cluster.dashboard.local`), so the two modes and the
Grafana JSON show the same thing. Metric names come from docs/design.md, "Metrics".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from cluster.metrics.exporters import RUN_INFO_NAME

Op = Literal["rate", "value", "hist_mean", "hist_quantile"]


@dataclass(frozen=True)
class Query:
    """One line (or one line per label value) of a chart.

    Attributes:
        op: "rate" = per-second increase of a counter; "value" = a gauge (or a counter's
            running total); "hist_mean" / "hist_quantile" = mean / quantile of a histogram's
            observations over the rate window.
        metric: the exposed metric name (histograms by their base name).
        by: labels that split the line, e.g. ("actor",); () sums everything into one line.
        legend: line name; `{label}` is replaced by the label's value.
        agg: how series that share the `by` labels combine ("sum" or "max").
        q: the quantile for hist_quantile.
    """

    op: Op
    metric: str
    by: tuple[str, ...] = ()
    legend: str = ""
    agg: Literal["sum", "max"] = "sum"
    q: float = 0.5

    def promql(self, window: str = "15s") -> str:
        """The PromQL expression; `window` is rate()'s range ("15s", "$__rate_interval")."""
        by = f" by ({', '.join(self.by)})" if self.by else ""
        if self.op == "rate":
            return f"sum{by} (rate({self.metric}[{window}]))"
        if self.op == "value":
            return f"{self.agg}{by} ({self.metric})"
        if self.op == "hist_mean":
            m = self.metric
            return f"sum{by} (rate({m}_sum[{window}])) / sum{by} (rate({m}_count[{window}]))"
        le_by = ", ".join((*self.by, "le"))
        buckets = f"rate({self.metric}_bucket[{window}])"
        return f"histogram_quantile({self.q}, sum by ({le_by}) ({buckets}))"

    def name_for(self, labels: dict[str, str]) -> str:
        """The legend text for one series with these labels."""
        text = self.legend or self.metric
        for key in self.by:
            text = text.replace("{" + key + "}", labels.get(key, "?"))
        return text


@dataclass(frozen=True)
class Panel:
    """One chart: a title a person reads at a glance, the unit of its y axis, its queries.

    Attributes:
        y_min: the y axis always includes this value (0 for rates and counts); None = data only.
        y_max: the y axis always includes this value (1 for fractions); None = data only.
        algos: the algorithms that feed this panel (() = every one); a run whose learner
            names its algorithm (credit_run_info) gets only its own panels.
    """

    id: str
    title: str
    unit: str
    queries: tuple[Query, ...]
    description: str = ""
    y_min: float | None = 0.0
    y_max: float | None = None
    algos: tuple[str, ...] = ()

    def shown_for(self, algos: set[str]) -> bool:
        """Whether a run of `algos` (empty: not known) shows this panel."""
        return not self.algos or not algos or bool(algos & set(self.algos))


RUN_INFO = RUN_INFO_NAME  # the learner's {algo, family} gauge (`LearnerMetrics`)

# The learning panels first: what a learner's user looks at before anything else.
PANELS: tuple[Panel, ...] = (
    Panel(
        "test_win_rate",
        "Test win rate",
        "fraction (0-1)",
        (Query("value", "credit_test_win_rate", legend="win rate", agg="max"),),
        "Fraction of greedy test episodes won.",
        y_max=1.0,
    ),
    Panel(
        "test_return",
        "Test return",
        "return",
        (Query("value", "credit_test_return", legend="mean return", agg="max"),),
        "Mean return of the greedy test episodes.",
        y_min=None,
    ),
    Panel(
        "env_steps",
        "Env steps/s per actor",
        "steps/s",
        (Query("rate", "credit_env_steps_total", ("actor",), "actor {actor}"),),
        "Environment steps per second each rollout actor completes (counted per episode).",
    ),
    Panel(
        "actor_episodes",
        "Episodes/s per actor",
        "episodes/s",
        (Query("rate", "credit_episodes_total", ("actor",), "actor {actor}"),),
        "Episodes per second each rollout actor finishes and sends to the buffer.",
    ),
    Panel(
        "buffer_inserts",
        "Episodes inserted per table",
        "episodes/s",
        (Query("rate", "credit_buffer_inserts_total", ("table",), "{table}"),),
        "Episodes per second the buffer service accepted, per table.",
    ),
    Panel(
        "buffer_fill",
        "Buffer fill per table",
        "episodes",
        (Query("value", "credit_buffer_size_episodes", ("table",), "{table}"),),
        "Episodes held by each buffer table.",
    ),
    Panel(
        "buffer_flow",
        "Buffer samples and rejections",
        "per second",
        (
            Query("rate", "credit_buffer_samples_total", ("table",), "sampled {table}"),
            Query("rate", "credit_buffer_rejected_total", ("reason",), "rejected: {reason}"),
        ),
        "Samples drawn per table and refused inserts per reason.",
    ),
    Panel(
        "policy_lag",
        "Policy lag",
        "versions",
        (
            Query("hist_mean", "credit_policy_lag_versions", legend="mean"),
            Query("hist_quantile", "credit_policy_lag_versions", legend="p95", q=0.95),
        ),
        "Learner version minus the version that collected each trained episode (replayed "
        "episodes are thousands of versions old on long runs).",
    ),
    Panel(
        "learner_updates",
        "Learner updates/s",
        "updates/s",
        (Query("rate", "credit_learner_updates_total", legend="updates"),),
        "Gradient updates per second.",
    ),
    Panel(
        "update_seconds",
        "Learner update time",
        "s",
        (
            Query("hist_mean", "credit_learner_update_seconds", legend="mean"),
            Query("hist_quantile", "credit_learner_update_seconds", legend="p95", q=0.95),
        ),
        "Wall time of one learner update.",
    ),
    Panel(
        "losses",
        "Losses",
        "loss",
        (Query("value", "credit_loss", ("name",), "{name}", agg="max"),),
        "Last value of each loss term.",
        y_min=None,
    ),
    Panel(
        "kl_masked",
        "KL-masked fraction (EM-CAC)",
        "fraction (0-1)",
        (Query("value", "credit_kl_masked_fraction", legend="masked", agg="max"),),
        "Fraction of timesteps whose advantage the KL mask zeroed.",
        y_max=1.0,
        algos=("emcac",),
    ),
    Panel(
        "actor_restarts",
        "Actor restarts",
        "restarts",
        (Query("value", "credit_actor_restarts_total", legend="restarts (total)"),),
        "Rollout actors restarted since the run began.",
    ),
    Panel(
        "weights_version",
        "Weights version",
        "version",
        (Query("value", "credit_weights_version", ("component",), "{component}", agg="max"),),
        "Policy version held by the learner and by each actor.",
    ),
)


def metric_names() -> set[str]:
    """Every exposed metric name the panels read (histograms by their base name)."""
    return {q.metric for p in PANELS for q in p.queries}

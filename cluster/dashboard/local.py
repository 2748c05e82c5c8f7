"""The dashboard without Prometheus: scrape the exporters directly and keep a short history.

`ScrapeHistory.scrape_once` reads every target's /metrics (Prometheus text format, parsed with
`prometheus_client.parser`) into one timestamped snapshot; `evaluate` turns the snapshots into
the same series a PromQL query of `cluster.dashboard.panels` would give (rates over a window,
histogram means and quantiles), so a chart looks the same with and without Prometheus.
"""

from __future__ import annotations

import logging
import math
import threading
import time
import urllib.request
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from prometheus_client.parser import text_string_to_metric_families

from cluster.dashboard.panels import Query

log = logging.getLogger(__name__)

Labels = tuple[tuple[str, str], ...]
Key = tuple[str, Labels]  # (sample name, sorted labels incl. instance)
Point = tuple[float, float]


@dataclass(frozen=True)
class Snapshot:
    """Every sample of every target at one time (unix seconds)."""

    t: float
    samples: dict[Key, float]


def parse_exposition(text: str, instance: str) -> dict[Key, float]:
    """Prometheus text format -> {(sample name, labels + instance): value}."""
    out: dict[Key, float] = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            labels = dict(s.labels, instance=instance)
            out[(s.name, tuple(sorted(labels.items())))] = float(s.value)
    return out


def fetch(target: str, timeout_s: float = 2.0) -> str:
    """GET http://target/metrics as text."""
    with urllib.request.urlopen(f"http://{target}/metrics", timeout=timeout_s) as r:
        return r.read().decode("utf-8", errors="replace")


class ScrapeHistory:
    """Snapshots of the exporters over the last `history_s` seconds.

    Args:
        targets: returns the current "host:port" list (re-read each scrape, so a file-SD
            file that the launcher rewrites is followed).
        history_s: how much history to keep.
        fetcher: target -> exposition text (tests may pass their own).
    """

    def __init__(
        self,
        targets: Callable[[], Sequence[str]],
        history_s: float = 600.0,
        fetcher: Callable[[str], str] = fetch,
    ) -> None:
        self._targets = targets
        self._fetch = fetcher
        self.history_s = history_s
        self._snaps: deque[Snapshot] = deque()
        self._lock = threading.Lock()
        self.errors: dict[str, str] = {}
        self.last_targets: list[str] = []

    def scrape_once(self, now: float | None = None) -> Snapshot:
        """Scrape every target once and append the snapshot; unreachable targets are noted."""
        samples: dict[Key, float] = {}
        errors: dict[str, str] = {}
        try:
            targets = list(self._targets())
        except (OSError, ValueError) as e:
            targets, errors["targets"] = [], str(e)
        for target in targets:
            try:
                samples.update(parse_exposition(self._fetch(target), target))
            except (OSError, ValueError) as e:
                errors[target] = str(e)
        snap = Snapshot(time.time() if now is None else now, samples)
        with self._lock:
            if samples:  # nothing answered: keep the history (a finished run's stays shown)
                self._snaps.append(snap)
            while self._snaps and self._snaps[0].t < self._snaps[-1].t - self.history_s:
                self._snaps.popleft()
            self.errors, self.last_targets = errors, targets
        return snap

    def snapshots(self) -> list[Snapshot]:
        with self._lock:
            return list(self._snaps)

    def run(self, interval_s: float, stop: threading.Event) -> None:
        """Scrape every `interval_s` seconds until `stop` is set (a thread's target)."""
        while not stop.is_set():
            self.scrape_once()
            stop.wait(interval_s)


def _group(labels: Labels, by: tuple[str, ...]) -> Labels:
    d = dict(labels)
    return tuple((k, d.get(k, "")) for k in by)


def _values(snap: Snapshot, name: str) -> dict[Labels, float]:
    return {labels: v for (n, labels), v in snap.samples.items() if n == name}


def _rates(older: Snapshot, newer: Snapshot, name: str) -> dict[Labels, float]:
    """Per-series per-second increase of counter `name` between two snapshots."""
    dt = newer.t - older.t
    if dt <= 0:
        return {}
    before = _values(older, name)
    out = {}
    for labels, v in _values(newer, name).items():
        if labels in before:
            delta = v - before[labels]
            out[labels] = (v if delta < 0 else delta) / dt  # a counter reset starts from 0
    return out


def _combine(series: dict[Labels, float], by: tuple[str, ...], agg: str) -> dict[Labels, float]:
    out: dict[Labels, float] = {}
    for labels, v in series.items():
        key = _group(labels, by)
        out[key] = v if key not in out else (max(out[key], v) if agg == "max" else out[key] + v)
    return out


def bucket_quantile(q: float, buckets: dict[float, float]) -> float:
    """Quantile from cumulative bucket counts {le: count}, as PromQL's histogram_quantile."""
    les = sorted(buckets)
    if not les or les[-1] != math.inf:
        return math.nan
    total = buckets[math.inf]
    if total <= 0:
        return math.nan
    rank = q * total
    prev_le, prev_count = 0.0, 0.0
    for le in les:
        count = buckets[le]
        if count >= rank:
            if le == math.inf:
                return les[-2] if len(les) > 1 else math.nan
            if le <= 0:
                return le
            width = count - prev_count
            frac = (rank - prev_count) / width if width > 0 else 1.0
            return prev_le + (le - prev_le) * frac
        prev_le, prev_count = le, count
    return math.nan


def _point(query: Query, older: Snapshot | None, newer: Snapshot) -> dict[Labels, float]:
    if query.op == "value":
        return _combine(_values(newer, query.metric), query.by, query.agg)
    if older is None:
        return {}
    if query.op == "rate":
        return _combine(_rates(older, newer, query.metric), query.by, "sum")
    if query.op == "hist_mean":
        s = _combine(_rates(older, newer, query.metric + "_sum"), query.by, "sum")
        c = _combine(_rates(older, newer, query.metric + "_count"), query.by, "sum")
        return {k: s[k] / c[k] for k in c if c[k] > 0 and k in s}
    rates = _rates(older, newer, query.metric + "_bucket")
    per_group: dict[Labels, dict[float, float]] = {}
    for labels, v in rates.items():
        le = float(dict(labels).get("le", "nan"))
        buckets = per_group.setdefault(_group(labels, query.by), {})
        buckets[le] = buckets.get(le, 0.0) + v
    out = {k: bucket_quantile(query.q, b) for k, b in per_group.items()}
    return {k: v for k, v in out.items() if not math.isnan(v)}


def evaluate(
    query: Query, snaps: Sequence[Snapshot], window_s: float, since: float = 0.0
) -> dict[str, list[Point]]:
    """The series `query` yields over `snaps` (oldest first): legend name -> [(t, value)].

    Args:
        query: what to compute.
        snaps: snapshots, oldest first.
        window_s: rate window: each point compares with the oldest snapshot at most this old.
        since: drop points before this time.
    """
    out: dict[str, list[Point]] = {}
    j = 0
    for i, snap in enumerate(snaps):
        while j < i and snaps[j].t < snap.t - window_s:
            j += 1
        if snap.t < since:
            continue
        older = snaps[j] if j < i else None
        for labels, value in _point(query, older, snap).items():
            if math.isfinite(value):
                out.setdefault(query.name_for(dict(labels)), []).append((snap.t, value))
    return out

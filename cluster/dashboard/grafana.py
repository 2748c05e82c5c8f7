"""Build `deploy/grafana/credit.json` from the dashboard's panels, so both show the same.

    python -m cluster.dashboard.grafana > deploy/grafana/credit.json

The JSON is a Grafana dashboard (schema 39) with a `datasource` template variable, one
time-series panel per `cluster.dashboard.panels.PANELS` entry and rates over
`$__rate_interval`; tests check the committed file equals this output.
"""

from __future__ import annotations

import json
from typing import Any

from cluster.dashboard.panels import PANELS, Panel

GRAFANA_UNITS = {"s": "s", "fraction (0-1)": "percentunit", "steps/s": "short"}
WIDTH, HEIGHT, PER_ROW = 8, 8, 3


def _panel(panel: Panel, index: int) -> dict[str, Any]:
    refs = "ABCDEFGH"
    defaults: dict[str, Any] = {
        "unit": GRAFANA_UNITS.get(panel.unit, "short"),
        "custom": {"axisLabel": panel.unit, "lineWidth": 2, "fillOpacity": 0},
        "noValue": "no data yet",
    }
    if panel.y_min is not None:
        defaults["min"] = panel.y_min
    if panel.y_max is not None:
        defaults["max"] = panel.y_max
    return {
        "id": index + 1,
        "type": "timeseries",
        "title": f"{panel.title} ({panel.unit})",
        "description": panel.description,
        "datasource": {"type": "prometheus", "uid": "${datasource}"},
        "gridPos": {
            "x": (index % PER_ROW) * WIDTH,
            "y": (index // PER_ROW) * HEIGHT,
            "w": WIDTH,
            "h": HEIGHT,
        },
        "fieldConfig": {"defaults": defaults, "overrides": []},
        "options": {
            "legend": {"displayMode": "list", "placement": "bottom", "calcs": ["lastNotNull"]},
            "tooltip": {"mode": "multi"},
        },
        "targets": [
            {
                "refId": refs[i],
                "datasource": {"type": "prometheus", "uid": "${datasource}"},
                "expr": q.promql("$__rate_interval"),
                "legendFormat": (q.legend or q.metric).replace("{", "{{").replace("}", "}}"),
            }
            for i, q in enumerate(panel.queries)
        ],
    }


def dashboard() -> dict[str, Any]:
    """The Grafana dashboard model."""
    return {
        "uid": "credit-live",
        "title": "credit — live training",
        "description": "Actors, buffer service and learner of a credit run (docs/design.md).",
        "tags": ["credit", "marl"],
        "timezone": "browser",
        "refresh": "5s",
        "time": {"from": "now-15m", "to": "now"},
        "schemaVersion": 39,
        "version": 1,
        "editable": True,
        "templating": {
            "list": [
                {
                    "name": "datasource",
                    "label": "Prometheus",
                    "type": "datasource",
                    "query": "prometheus",
                    "current": {},
                    "hide": 0,
                }
            ]
        },
        "panels": [_panel(p, i) for i, p in enumerate(PANELS)],
    }


def render() -> str:
    """The file's exact text."""
    return json.dumps(dashboard(), indent=2, ensure_ascii=False) + "\n"


if __name__ == "__main__":
    import sys

    sys.stdout.write(render())

"""End to end: headless Chromium reads the live dashboard of a running cluster training.

`running_training` starts `credit train --mode cluster` (Ray rollout actors, the buffer
service, the learner) on skirmish/3m; the dashboard reads its exporters directly or through a
real Prometheus. The screenshot lands in test-artifacts/.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import pytest

from cluster.dashboard.server import (
    DashboardConfig,
    DashboardServer,
    ExporterSource,
    PrometheusSource,
)
from cluster.metrics import discovery
from cluster.metrics import prometheus as prom
from tests.cluster.browser import NEEDS_CHROMIUM, chromium
from tests.cluster.polling import wait_for

ROOT = Path(__file__).resolve().parents[2]
ARTIFACTS = ROOT / "test-artifacts"
# Panels a running RDN training feeds (the KL mask is EM-CAC's and stays at its initial 0).
FED_PANELS = (
    "env_steps",
    "actor_episodes",
    "buffer_inserts",
    "buffer_fill",
    "policy_lag",
    "learner_updates",
    "update_seconds",
    "losses",
    "test_return",
    "test_win_rate",
    "kl_masked",
    "actor_restarts",
    "weights_version",
)

pytestmark = NEEDS_CHROMIUM


@pytest.fixture(scope="module")
def browser():
    with chromium() as driver:
        yield driver


def panel_state(driver) -> dict[str, dict]:
    script = """return Array.from(document.querySelectorAll('.panel')).map(p => ({
        id: p.dataset.panel, points: Number(p.dataset.points || 0),
        series: Number(p.dataset.series || 0), text: p.innerText}));"""
    return {p["id"]: p for p in driver.execute_script(script)}


def check_dashboard(driver, url: str, shot: str) -> dict[str, dict]:
    driver.get(url)
    assert "credit" in driver.title

    def fed() -> dict | None:
        s = panel_state(driver)
        # > 1 point everywhere; a few more on the busiest chart so the picture shows a line.
        ok = all(s.get(i, {}).get("points", 0) > 1 for i in FED_PANELS)
        return s if ok and s["env_steps"]["points"] >= 16 else None

    state = wait_for(fed, timeout_s=90, what="every actor/learner panel to hold data points")
    ARTIFACTS.mkdir(exist_ok=True)
    (ARTIFACTS / ".gitignore").write_text("*\n")
    height = driver.execute_script("return document.documentElement.scrollHeight")
    # The whole page in one picture: make the viewport as tall as the page.
    metrics = {"width": 1600, "height": int(height) + 20, "deviceScaleFactor": 1, "mobile": False}
    driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", metrics)
    time.sleep(0.5)  # let the resize re-layout before the picture (not an assertion)
    driver.save_screenshot(str(ARTIFACTS / shot))
    (ARTIFACTS / shot).with_suffix(".json").write_text(json.dumps(state, indent=2))
    assert (ARTIFACTS / shot).stat().st_size > 10_000
    for pid, p in state.items():
        if p["points"] == 0:
            assert "no data yet" in p["text"], pid  # empty charts say so
        else:
            assert "no data yet" not in p["text"], pid
    assert "actor 0" in state["env_steps"]["text"] and "actor 1" in state["env_steps"]["text"]
    assert "steps/s" in state["env_steps"]["text"]
    return state


def test_dashboard_scraping_exporters(running_training, browser):
    cfg = DashboardConfig(port=0, range_s=120)
    server = DashboardServer(cfg, ExporterSource(lambda: running_training, cfg)).start()
    try:
        check_dashboard(browser, server.url, "dashboard-exporters.png")
    finally:
        server.close()


@pytest.mark.skipif(shutil.which("prometheus") is None, reason="prometheus not on PATH")
def test_dashboard_reading_prometheus(running_training, browser, tmp_path):
    sd = discovery.write_file_sd(
        tmp_path / "sd.json", [discovery.parse_target(t) for t in running_training]
    )
    state = prom.start(prom.PrometheusConfig(port=0, sd_file=str(sd), state_dir=str(tmp_path)))
    cfg = DashboardConfig(port=0, range_s=120)
    server = DashboardServer(cfg, PrometheusSource(state.url, cfg)).start()
    try:
        check_dashboard(browser, server.url, "dashboard-prometheus.png")
    finally:
        server.close()
        prom.stop(tmp_path)

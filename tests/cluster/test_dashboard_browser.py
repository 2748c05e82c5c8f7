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
from cluster.metrics import discovery, exporters
from cluster.metrics import http as mhttp
from cluster.metrics import prometheus as prom
from tests.cluster.browser import NEEDS_CHROMIUM, chromium
from tests.cluster.polling import wait_for

ROOT = Path(__file__).resolve().parents[2]
ARTIFACTS = ROOT / "test-artifacts"
# Panels a running RDN training feeds (the KL mask is EM-CAC's: not shown for RDN).
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
    "actor_restarts",
    "weights_version",
)

pytestmark = NEEDS_CHROMIUM


@pytest.fixture(scope="module")
def browser():
    with chromium() as driver:
        yield driver


def panel_state(driver) -> dict[str, dict]:
    script = """return Array.from(document.querySelectorAll('#grid .panel')).map(p => ({
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
    _shot(driver, shot)
    (ARTIFACTS / shot).with_suffix(".json").write_text(json.dumps(state, indent=2))
    assert (ARTIFACTS / shot).stat().st_size > 10_000
    for pid, p in state.items():
        if p["points"] == 0:
            assert "no data yet" in p["text"], pid  # empty charts say so
        else:
            assert "no data yet" not in p["text"], pid
    assert "actor 0" in state["env_steps"]["text"] and "actor 1" in state["env_steps"]["text"]
    assert "steps/s" in state["env_steps"]["text"]
    assert list(state)[:2] == ["test_win_rate", "test_return"]  # the learning panels first
    assert "kl_masked" not in state  # EM-CAC's panel, not RDN's
    return state


@pytest.mark.default_tier(reason="watches the default tier's live cluster run")
def test_dashboard_scraping_exporters(running_training, browser):
    cfg = DashboardConfig(port=0, range_s=120)
    server = DashboardServer(cfg, ExporterSource(lambda: running_training, cfg)).start()
    try:
        check_dashboard(browser, server.url, "dashboard-exporters.png")
    finally:
        server.close()


@pytest.mark.skipif(shutil.which("prometheus") is None, reason="prometheus not on PATH")
@pytest.mark.default_tier(reason="watches the default tier's live cluster run")
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


def _shot(driver, name: str) -> None:
    """The whole page in one picture (the viewport made as tall as the page)."""
    ARTIFACTS.mkdir(exist_ok=True)
    (ARTIFACTS / ".gitignore").write_text("*\n")
    height = driver.execute_script("return document.documentElement.scrollHeight")
    metrics = {"width": 1600, "height": int(height) + 20, "deviceScaleFactor": 1, "mobile": False}
    driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", metrics)
    time.sleep(0.5)  # let the resize re-layout before the picture (not an assertion)
    driver.save_screenshot(str(ARTIFACTS / name))


def test_a_qmix_run_long_lags_and_its_finish(browser, tmp_path):
    """A QMIX learner's real exporter with replayed episodes 1000-2000 versions old: its
    panels (no EM-CAC KL mask), learning panels first, a p95 lag in the thousands; then the
    process is gone and its summary.json written: the page says it finished, with its final
    numbers, and shows no connection errors."""
    learner = exporters.LearnerMetrics(algo="qmix", family="value")
    ep = mhttp.serve(learner.registry)
    cfg = DashboardConfig(port=0, range_s=120, scrape_interval_s=0.5, rate_window_s=5)
    source = ExporterSource(lambda: [f"{ep[0]}:{ep[1]}"], cfg, run_dir=tmp_path)
    server = DashboardServer(cfg, source).start()
    try:
        for version in range(1, 41):
            learner.record_update(0.01, {"loss_td": 1.0 / version}, weights_version=version)
            learner.record_policy_lag(range(1000, 2001, 50))
            learner.record_test(10.0 + version / 4, min(1.0, version / 40))
            time.sleep(0.1)
        browser.get(server.url)
        state = wait_for(
            lambda: (s := panel_state(browser)).get("policy_lag", {}).get("points", 0) > 1 and s,
            timeout_s=60,
            what="the policy-lag panel to hold points",
        )
        assert list(state)[:2] == ["test_win_rate", "test_return"]
        assert "kl_masked" not in state and "losses" in state
        legend = dict(
            browser.execute_script(
                "const items = document.querySelectorAll('#panel-policy_lag .legend .item');"
                "return Array.from(items).map(i => [i.childNodes[1].textContent,"
                " i.querySelector('.value').textContent]);"
            )
        )
        assert 1850 < float(legend["p95"]) < 2050, legend  # exact p95 of the lags: 1950
        final = {"algo": "qmix", "env": "skirmish/3m", "t_env": 40_000, "wall_s": 95.0}
        final |= {"final_test_return_mean": 20.0, "final_test_won_mean": 1.0}
        (tmp_path / "summary.json").write_text(json.dumps(final))
        mhttp.stop(ep)  # the training process ends
        banner = wait_for(
            lambda: browser.execute_script(
                "const r = document.getElementById('run');"
                "return !r.hidden && r.dataset.state === 'finished' && r.innerText;"
            ),
            timeout_s=30,
            what="the finished-run banner",
        )
        assert "Run finished at" in banner and "qmix on skirmish/3m" in banner, banner
        assert "40,000 env steps" in banner and "win rate 1.00" in banner, banner
        assert "test return 20.00" in banner, banner
        time.sleep(2 * cfg.refresh_s)  # more refreshes with every exporter refusing
        assert browser.execute_script("return document.getElementById('errors').hidden")
        page = browser.find_element("tag name", "body").text
        assert "Connection refused" not in page and "urlopen" not in page
        after = panel_state(browser)
        assert after["test_win_rate"]["points"] > 1  # the run's history stays drawn
        _shot(browser, "dashboard-finished.png")
    finally:
        server.close()
        mhttp.stop(ep)

"""The test tiers (tests/README.md): after a run of the default tier, name the tests that took
long enough to belong in `make test-slow`, so the rule is seen where it is broken."""

from __future__ import annotations

import pytest

# A default-tier test this long on the project's 2-core machine belongs in the slow tier
# (tests/README.md). Reported, never asserted: timings on a shared machine drift.
REPORT_OVER_S = 20.0

_durations: dict[str, float] = {}


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if report.when != "teardown" and not item.get_closest_marker("slow"):
        _durations[item.nodeid] = _durations.get(item.nodeid, 0.0) + report.duration


def pytest_terminal_summary(terminalreporter):
    long = sorted(((s, n) for n, s in _durations.items() if s > REPORT_OVER_S), reverse=True)
    if not long:
        return
    terminalreporter.section("tests that belong in the slow tier (tests/README.md)")
    for seconds, nodeid in long:
        terminalreporter.write_line(f"{seconds:6.1f} s  {nodeid}  (not marked slow)")

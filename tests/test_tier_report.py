"""The report in tests/conftest.py of default-tier tests long enough for the slow tier."""

from __future__ import annotations

from pathlib import Path

TESTS = """
import time
import pytest

def test_long_and_unmarked():
    time.sleep(0.6)

@pytest.mark.default_tier(reason="kept for a reason of its own")
def test_long_and_kept():
    time.sleep(0.6)

@pytest.mark.slow
def test_long_and_slow():
    time.sleep(0.6)

def test_short():
    pass
"""


def test_long_tests_are_named_and_the_kept_ones_apart_with_their_reason(pytester, monkeypatch):
    pytester.makeconftest((Path(__file__).parent / "conftest.py").read_text())
    pytester.makepyfile(test_tiers=TESTS)
    monkeypatch.setenv("CREDIT_TEST_REPORT_OVER_S", "0.3")
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider")
    result.assert_outcomes(passed=4)
    out = result.stdout.str()
    kept_at = out.index("long tests kept in the default tier on purpose")
    slow_at = out.index("tests that belong in the slow tier")
    assert kept_at < slow_at  # the exceptions first, then what to move
    kept, flagged = out[kept_at:slow_at], out[slow_at:]
    assert "test_long_and_kept  (kept for a reason of its own)" in kept
    assert "test_long_and_unmarked  (not marked slow)" in flagged
    assert "test_long_and_kept" not in flagged and "test_long_and_unmarked" not in kept
    assert "test_short" not in out and "test_long_and_slow" not in out

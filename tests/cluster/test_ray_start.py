"""Starting Ray from several of our processes at once: the shared auth token and the start lock.

Two `credit train --mode cluster` runs started together (as the two-runs Prometheus test does)
both create the token file of a fresh state folder and both start a private Ray instance."""

from __future__ import annotations

import logging
import multiprocessing
import time
from pathlib import Path

from cluster.launch import ray_cluster


def test_a_token_another_process_made_after_our_check_is_kept(tmp_path, monkeypatch):
    """The race: our `exists()` says no, then another process creates the token before we do.
    We must neither fail nor replace its token (Ray processes already read it)."""
    monkeypatch.setenv("CREDIT_STATE_DIR", str(tmp_path))
    theirs = "a" * 64
    token = ray_cluster.state_dir() / "ray_auth_token"
    token.parent.mkdir(parents=True)
    token.write_text(theirs)
    real_exists = Path.exists
    monkeypatch.setattr(Path, "exists", lambda p: False if p == token else real_exists(p))

    assert ray_cluster.token_path() == token
    assert token.read_text() == theirs
    assert [p.name for p in token.parent.iterdir()] == ["ray_auth_token"]  # no temporary left


def test_a_new_token_is_whole_and_private(tmp_path, monkeypatch):
    monkeypatch.setenv("CREDIT_STATE_DIR", str(tmp_path))
    token = ray_cluster.token_path()
    assert len(token.read_text()) == 64
    assert token.stat().st_mode & 0o777 == 0o600
    assert ray_cluster.token_path().read_text() == token.read_text()  # made once


def _hold_lock(path: str, held, release_at, hold_s: float) -> None:
    ray_cluster.start_lock_path = lambda: Path(path)
    with ray_cluster.local_start_lock():
        held.set()
        time.sleep(hold_s)
        release_at.value = time.monotonic()


def _start_holder(path: Path, hold_s: float):
    ctx = multiprocessing.get_context("fork")
    held, release_at = ctx.Event(), ctx.Value("d", 0.0)
    proc = ctx.Process(target=_hold_lock, args=(str(path), held, release_at, hold_s))
    proc.start()
    assert held.wait(30), "the child never took the lock"
    return proc, release_at


def test_a_second_start_waits_for_the_first_to_finish(tmp_path, monkeypatch):
    path = tmp_path / "start.lock"
    monkeypatch.setattr(ray_cluster, "start_lock_path", lambda: path)
    proc, release_at = _start_holder(path, hold_s=1.0)
    with ray_cluster.local_start_lock():
        entered = time.monotonic()
    proc.join(30)
    assert release_at.value > 0 and entered >= release_at.value


def test_a_start_lock_held_too_long_is_passed_with_a_warning(tmp_path, monkeypatch, caplog):
    path = tmp_path / "start.lock"
    monkeypatch.setattr(ray_cluster, "start_lock_path", lambda: path)
    proc, release_at = _start_holder(path, hold_s=5.0)
    try:
        with caplog.at_level(logging.WARNING), ray_cluster.local_start_lock(timeout_s=0.3):
            entered = time.monotonic()
        assert release_at.value == 0.0 and entered > 0
        assert "starting anyway" in caplog.text
    finally:
        proc.terminate()
        proc.join(30)


def test_a_lock_file_that_cannot_be_opened_does_not_stop_a_start(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(ray_cluster, "start_lock_path", lambda: tmp_path / "missing" / "x.lock")
    with caplog.at_level(logging.WARNING), ray_cluster.local_start_lock():
        pass
    assert "without the start lock" in caplog.text

"""Shared fixtures: one real cluster training for the tests that watch a live run."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cluster.metrics import discovery
from tests.cluster.polling import session_members, wait_for

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="session")
def running_training(tmp_path_factory):
    """A real cluster training (`credit train --mode cluster`, RDN on skirmish/3m, two Ray
    rollout actors, the buffer service, this learner); yields its four exporters as
    "host:port" (learner, actor 0, actor 1, buffer service) while it runs. Ended at last as a
    job scheduler ends one, with SIGTERM: it must exit 143 and take every process it started
    (Ray's included) with it."""
    pytest.importorskip("ray", reason="cluster mode needs ray")
    out = tmp_path_factory.mktemp("training")
    env = {**os.environ, "CREDIT_STATE_DIR": str(out / "state")}
    cmd = [sys.executable, "-m", "cluster.cli", "train", "--mode", "cluster", "--actors", "2"]
    cmd += ["--algo", "rdn", "--env", "skirmish/3m", "--t-max", "100000000"]
    cmd += ["--out", str(out / "run"), "--set", "run.test_interval=300"]
    cmd += ["--set", "run.test_episodes=4"]
    log = open(out / "train.log", "w")  # noqa: SIM115 - closed after the process
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=log, start_new_session=True)
    sd = out / "run" / "targets.json"
    try:
        targets = wait_for(
            lambda: (
                sd.exists() and len(discovery.read_file_sd(sd)) == 4 and discovery.read_file_sd(sd)
            ),
            timeout_s=180,
            what="the training's file-SD file",
        )
        yield [f"{h}:{p}" for h, p in targets]
    finally:
        proc.send_signal(signal.SIGTERM)  # a clean shutdown: actors, buffer service, Ray
        try:
            status = proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            status = None
        log.close()
        deadline = time.monotonic() + 30
        while (left := session_members(proc.pid)) and time.monotonic() < deadline:
            time.sleep(0.5)
        said = (out / "train.log").read_text(errors="replace")[-2000:]
        assert status == 143, f"SIGTERM: exit status {status}, not 143; the log ends:\n{said}"
        assert not left, f"processes of the run still running 30 s after it exited: {left}"

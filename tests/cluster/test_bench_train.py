"""`credit bench train`: the real loop's env steps per second and where its time went."""

import json
import subprocess
import sys

import pytest

from cluster.bench.train import breakdown
from learner.timers import Timers


def test_sections_nest_and_exclusive_seconds_subtract_the_inner_ones():
    t = Timers()
    t.reset(enabled=True)
    with t.section("update"):
        with t.section("backward"):
            pass
        with t.section("backward"):
            pass
    assert set(t.totals) == {"update", "update/backward"}
    assert t.counts["update/backward"] == 2
    own = t.exclusive()
    assert own["update"] == pytest.approx(t.totals["update"] - t.totals["update/backward"])
    assert list(t.iterate("sample", iter([1, 2]))) == [1, 2]
    assert t.counts["sample"] == 3  # two items and the exhausted call


def test_switched_off_records_nothing():
    t = Timers()
    with t.section("update"):
        pass
    assert not t.totals


def test_breakdown_puts_what_no_part_names_into_other():
    parts = breakdown({"act/env": 1.0, "update": 2.0, "update/backward": 0.5, "mystery": 0.25}, 4.0)
    assert parts["env"] == 1.0 and parts["forward"] == 2.0 and parts["backward"] == 0.5
    assert sum(parts.values()) == pytest.approx(4.0)
    assert parts["other"] == pytest.approx(0.5)


@pytest.mark.slow
def test_bench_train_runs_the_loop_and_its_parts_sum_to_the_wall_time(tmp_path):
    out = tmp_path / "train.json"
    cmd = [sys.executable, "-m", "cluster.cli", "bench", "train", "--env", "skirmish/3m"]
    cmd += ["--algo", "vdn", "--seeds", "2", "--steps", "700", "--test-interval", "400"]
    cmd += ["--save-interval", "400", "--out", str(out)]
    subprocess.run(cmd, check=True, capture_output=True, timeout=600)
    rec = json.loads(out.read_text())
    assert rec["benchmark"] == "train" and rec["seeds"] == 2 and rec["t_env"] >= 700
    assert rec["updates"] > 0 and rec["env_steps_per_s"] > 0 and rec["precision"] == "float32"
    parts = rec["parts_s"]
    assert set(parts) == {
        "env", "acting", "act_other", "sampling", "batching", "forward", "backward",
        "optimiser", "evaluation", "checkpoint", "other",
    }  # fmt: skip
    for name in ("env", "acting", "forward", "backward", "optimiser", "evaluation", "checkpoint"):
        assert parts[name] > 0, name
    assert rec["parts_sum_s"] == pytest.approx(rec["total_s"], rel=0.01)
    assert abs(parts["other"]) < 0.05 * rec["total_s"]  # the timers cover the loop
    assert rec["section_counts"]["update/backward"] == rec["updates"] * 1

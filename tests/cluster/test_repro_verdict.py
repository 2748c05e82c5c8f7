"""The redundancy verdict (`cluster.repro.verdict`) from synthetic evaluation logs in the
format of results/redundancy/table51/evals/*.jsonl: per-seed finals, the slope against
allied zerglings and its stratified interval, the flat / falls decisions, QMIX-nostate
against QMIX, and pairs that have not finished reported as missing."""

import json

import numpy as np
import pytest

from cluster.cli import main
from cluster.repro.curves import load_evals
from cluster.repro.redundancy import ENVS, write_figures
from cluster.repro.verdict import (
    FIGURE,
    Plan,
    bootstrap_interval,
    describe,
    slope_statistic,
    verdict,
)

T_MAX = 100_000
EVERY = 5_000
ZERGLINGS = {
    "skirmish/bane_vs_bane": 20,
    "skirmish/bane_med": 15,
    "skirmish/bane_small": 10,
    "skirmish/bane_no_z": 0,
}
OFFSETS = (-0.01, 0.0, 0.01)  # each seed's final win rate about its map's mean


def _write_log(evals, env: str, algo: str, finals: list[float], t_end: int = T_MAX) -> None:
    """An evaluation log every EVERY steps up to `t_end`: wins of 1.0 early (outside the
    last 10 evaluations, so that a final over the wrong evaluations shows), then seed k
    alternating finals[k] +- 0.05 (its mean over the last 10 evaluations is finals[k])."""
    rows = []
    ts = [*range(131, t_end, EVERY), t_end + 74]
    for i, t in enumerate(ts):
        last10 = i >= len(ts) - 10
        swing = 0.05 if i % 2 else -0.05
        won = [round(f + swing, 4) if last10 else 1.0 for f in finals]
        rows.append(
            {"env": env, "algo": algo, "t_env": t, "won": won, "returns": [10.0] * len(finals)}
            | {"wall_s": t / 100, "commit": "e88aee4843d6e0494242e7543fd767b4b219da7e"}
        )
    name = env.replace("/", "-")
    (evals / f"{name}__{algo}.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))


def _line(intercept: float, slope: float, env: str) -> list[float]:
    return [intercept + slope * ZERGLINGS[env] + d for d in OFFSETS]


@pytest.fixture
def evals(tmp_path):
    """RDN flat at 0.4 on all four maps; VDN falling 0.02 per zergling from 0.5; QMIX
    finished on bane_no_z only (its bane_vs_bane log stops at 60k); QMIX-nostate 0.4 above
    QMIX on bane_no_z; QMIX-nostate on bane_med with no QMIX log there."""
    d = tmp_path / "evals"
    d.mkdir()
    for env in ZERGLINGS:
        _write_log(d, env, "rdn", _line(0.4, 0.0, env))
        _write_log(d, env, "vdn", _line(0.5, -0.02, env))
    _write_log(d, "skirmish/bane_no_z", "qmix", [0.15, 0.2, 0.25])
    _write_log(d, "skirmish/bane_vs_bane", "qmix", [0.3, 0.3, 0.3], t_end=60_000)
    _write_log(d, "skirmish/bane_no_z", "qmix_ns", [0.55, 0.6, 0.65])
    _write_log(d, "skirmish/bane_med", "qmix_ns", [0.5, 0.5, 0.6])
    return d


def _verdict(evals) -> dict:
    algos = ["rdn", "vdn", "qmix", "qmix_ns"]
    curves = load_evals(evals, algos, list(ZERGLINGS), until=T_MAX)
    plan = Plan({(g, a): T_MAX for g in ZERGLINGS for a in algos}, reps=500)
    return verdict(curves, plan, ENVS)


def test_per_seed_finals_are_the_means_of_the_last_ten_evaluations(evals):
    v = _verdict(evals)
    cell = v["final"]["skirmish/bane_med"]["vdn"]
    assert cell["per_seed"] == pytest.approx([0.19, 0.2, 0.21])  # 0.5 - 0.02 * 15 +- 0.01
    assert cell["mean"] == pytest.approx(0.2) and cell["zerglings"] == 15
    assert 0.19 <= cell["ci"][0] < 0.2 < cell["ci"][1] <= 0.21
    assert v["slope"]["vdn"]["per_seed"][0] == pytest.approx([0.09, 0.1, 0.11])  # bane_vs_bane


def test_a_known_slope_is_recovered_and_judged(evals):
    v = _verdict(evals)
    vdn, rdn = v["slope"]["vdn"], v["slope"]["rdn"]
    assert vdn["maps"] == list(ZERGLINGS) and vdn["zerglings"] == [20, 15, 10, 0]
    assert vdn["slope"] == pytest.approx(-0.02, abs=1e-4)
    assert vdn["ci"][0] < -0.02 < vdn["ci"][1] < 0
    assert vdn["falls"] and not vdn["flat"] and not vdn["rises"]
    assert rdn["slope"] == pytest.approx(0.0, abs=1e-4)
    assert -0.01 <= rdn["ci"][0] < 0 < rdn["ci"][1] <= 0.01
    assert rdn["flat"] and not rdn["falls"]
    assert rdn["missing"] == [] and vdn["missing"] == []
    said = v["statements"]
    assert said["rdn_flat"]["answer"] == "yes" and said["vdn_falls"]["answer"] == "yes"


def test_pairs_not_finished_are_reported_missing_without_a_number(evals):
    v = _verdict(evals)
    qmix = v["slope"]["qmix"]
    assert "slope" not in qmix and "ci" not in qmix and qmix["maps"] == ["skirmish/bane_no_z"]
    why = {m["env"]: m["why"] for m in qmix["missing"]}
    assert why["skirmish/bane_vs_bane"] == "unfinished: 60074 of 100000 env steps"
    assert why["skirmish/bane_med"] == why["skirmish/bane_small"] == "no evaluation log"
    assert v["statements"]["qmix_falls"] == {"answer": "not yet", "missing": qmix["missing"]}
    med = v["qmix_ns_minus_qmix"]["skirmish/bane_med"]
    assert med == {
        "missing": [{"env": "skirmish/bane_med", "algo": "qmix", "why": "no evaluation log"}]
    }
    assert v["statements"]["qmix_ns_beats_qmix"]["skirmish/bane_med"]["answer"] == "not yet"
    finished = {(p["env"], p["algo"]) for p in v["finished"]}
    assert ("skirmish/bane_vs_bane", "qmix") not in finished
    assert ("skirmish/bane_no_z", "qmix") in finished and len(finished) == 11


def test_qmix_nostate_against_qmix(evals):
    v = _verdict(evals)
    d = v["qmix_ns_minus_qmix"]["skirmish/bane_no_z"]
    assert d["qmix_ns"] == pytest.approx([0.55, 0.6, 0.65]) and d["qmix"] == [0.15, 0.2, 0.25]
    assert d["difference"] == pytest.approx(0.4)
    assert 0.3 <= d["ci"][0] < 0.4 < d["ci"][1] <= 0.5 and d["beats"]
    assert d["p_qmix_ns_better"] == 1.0  # every QMIX-nostate seed above every QMIX seed
    assert v["statements"]["qmix_ns_beats_qmix"]["skirmish/bane_no_z"]["answer"] == "yes"


def test_a_falling_slope_is_not_flat_and_a_wide_interval_is_undecided(tmp_path):
    evals = tmp_path / "evals"
    evals.mkdir()
    for env in ("skirmish/bane_vs_bane", "skirmish/bane_no_z"):
        _write_log(evals, env, "rdn", _line(0.5, -0.015, env))  # falls: not flat
        n = ZERGLINGS[env]
        _write_log(evals, env, "vdn", [0.1, 0.9, 0.5] if n else [0.5, 0.1, 0.9])  # wide
    algos = ["rdn", "vdn"]
    envs = ["skirmish/bane_vs_bane", "skirmish/bane_no_z"]
    plan = Plan({(g, a): T_MAX for g in envs for a in algos}, reps=500)
    v = verdict(load_evals(evals, algos, envs, until=T_MAX), plan, ENVS)
    rdn = v["slope"]["rdn"]
    assert rdn["slope"] == pytest.approx(-0.015, abs=1e-4) and rdn["falls"] and not rdn["flat"]
    rdn_flat = v["statements"]["rdn_flat"]  # interval below -0.01, two maps missing
    assert rdn_flat["answer"] == "not yet" and rdn_flat["so_far"] == "no"
    assert rdn_flat["ci"] == rdn["ci"] and len(rdn_flat["missing"]) == 2
    assert "rdn_flat: not yet (2 pairs missing; no [" in "\n".join(describe(v))
    assert [m["env"] for m in rdn["missing"]] == ["skirmish/bane_med", "skirmish/bane_small"]
    vdn = v["slope"]["vdn"]
    assert vdn["ci"][0] < -0.01 and vdn["ci"][1] > 0.01
    assert v["statements"]["vdn_falls"]["so_far"] == "undecided"


def test_the_slope_interval_resamples_seeds_within_each_map():
    # every seed of a map has the same final win rate: resampling seeds within each map
    # cannot move the slope (pooling the points of all maps would)
    x, finals = [20, 10, 0], ([0.1] * 3, [0.3] * 3, [0.5] * 3)
    stat = slope_statistic(x)
    assert stat(*finals) == pytest.approx(np.polyfit(np.repeat(x, 3), np.ravel(finals), 1)[0])
    slope, ci = bootstrap_interval(finals, stat, Plan({}, reps=200))
    assert slope == pytest.approx(-0.02) and ci == pytest.approx([-0.02, -0.02])


def test_summarise_only_writes_the_verdict_and_its_figure(evals, capsys):
    out = evals.parent
    argv = ["repro", "redundancy", "--envs", "skirmish/bane_vs_bane,skirmish/bane_no_z"]
    argv += ["--algos", "rdn,qmix", "--out", str(out), "--summarise-only", "--t-max", str(T_MAX)]
    assert main([*argv, "--bootstrap-reps", "50"]) == 0
    v = json.loads((out / "summary.json").read_text())["verdict"]
    assert v["bootstrap"]["reps"] == 50
    why = "unfinished: 60074 of 100000 env steps"
    assert v["missing"] == [{"env": "skirmish/bane_vs_bane", "algo": "qmix", "why": why}]
    assert v["slope"]["rdn"]["maps"] == ["skirmish/bane_vs_bane", "skirmish/bane_no_z"]
    assert (out / FIGURE).stat().st_size > 10_000
    printed = capsys.readouterr().out
    # RDN's two finished maps read as flat; bane_med and bane_small are still to run
    assert "rdn_flat: not yet (2 pairs missing; yes [" in printed
    assert "qmix_falls: not yet (3 pairs missing)\n" in printed


def test_figures_without_a_plan_take_every_curve_as_finished(evals, tmp_path):
    curves = load_evals(evals, ["qmix"], ["skirmish/bane_vs_bane", "skirmish/bane_no_z"])
    summary: dict = {}
    files = write_figures(
        curves, ["skirmish/bane_vs_bane", "skirmish/bane_no_z"], tmp_path, summary
    )
    assert files[-1] == FIGURE and (tmp_path / FIGURE).exists()
    assert summary["verdict"]["slope"]["qmix"]["maps"] == [
        "skirmish/bane_vs_bane",
        "skirmish/bane_no_z",
    ]


def test_a_pair_short_of_its_seed_groups_counts_as_missing(tmp_path):
    # RDN on bane_small has 2 of its 3 seeds (a seed group still to run): its values are
    # not in the verdict's finals or slope until the third has run
    evals = tmp_path / "evals"
    evals.mkdir()
    for env in ("skirmish/bane_vs_bane", "skirmish/bane_no_z"):
        _write_log(evals, env, "rdn", _line(0.4, 0.0, env))
    _write_log(evals, "skirmish/bane_small", "rdn", [0.9, 0.95])
    envs = ["skirmish/bane_vs_bane", "skirmish/bane_small", "skirmish/bane_no_z"]
    curves = load_evals(evals, ["rdn"], envs, until=T_MAX)
    plan = Plan({(g, "rdn"): T_MAX for g in envs}, reps=200, seeds=3)
    v = verdict(curves, plan, ENVS)
    assert v["missing"] == [{"env": "skirmish/bane_small", "algo": "rdn", "why": "2 of 3 seeds"}]
    assert "skirmish/bane_small" not in v["final"]
    assert v["slope"]["rdn"]["maps"] == ["skirmish/bane_vs_bane", "skirmish/bane_no_z"]
    assert v["statements"]["rdn_flat"]["answer"] == "not yet"
    # the same logs planned as 2 seeds per pair: bane_small has finished
    v2 = verdict(curves, Plan(plan.t_max, reps=200, seeds=2), ENVS)
    assert v2["final"]["skirmish/bane_small"]["rdn"]["per_seed"] == pytest.approx([0.9, 0.95])


def test_the_printed_answer_counts_missing_pairs_in_words():
    from cluster.repro.verdict import _answer

    one = {"env": "skirmish/bane_med", "algo": "qmix", "why": "not run"}
    assert _answer({"missing": [one]}) == "not yet (1 pair missing)"
    so_far = {"missing": [one, one], "ci": [0.1, 0.2], "answer": "not yet", "so_far": "no"}
    assert _answer(so_far) == "not yet (2 pairs missing; no [0.100, 0.200] from the finished pairs)"

"""`credit repro redundancy`: the seed's Figs. 5.6-5.9 and the final-win-rate chart from
curves, the generated maps of --zerglings, and a tiny end-to-end run."""

import dataclasses
import json

import numpy as np
import pytest

from cluster.cli import main
from cluster.repro.curves import Curve, headings, logged
from cluster.repro.redundancy import final_stats, ordered, write_figures, zergling_envs


def _curve(algo: str, env: str, won: list[list[float]]) -> Curve:
    k = len(won)
    return Curve(algo, env, [1000 * (i + 1) for i in range(k)], won, won, 1.0)


def test_maps_run_from_most_to_fewest_zerglings_and_generated_ones_fit_in():
    envs = ["skirmish/bane_no_z", "skirmish/bane_z30", "skirmish/bane_vs_bane", "skirmish/bane_med"]
    assert ordered(envs) == [
        "skirmish/bane_z30",
        "skirmish/bane_vs_bane",
        "skirmish/bane_med",
        "skirmish/bane_no_z",
    ]
    assert zergling_envs("0, 5,30") == ["skirmish/bane_z0", "skirmish/bane_z5", "skirmish/bane_z30"]


def test_figures_and_their_numbers(tmp_path):
    # 12 evaluations x 4 seeds; the last 10 evaluations of seed k win k / 4 of the time
    won = [[0.0] * 4] * 2 + [[0.0, 0.25, 0.5, 0.75]] * 10
    curves = [
        _curve("rdn", "skirmish/bane_vs_bane", won),
        _curve("rdn", "skirmish/bane_no_z", [[1.0] * 4] * 12),
        _curve("vdn", "skirmish/bane_vs_bane", [[0.5, 0.5, 1.0, 1.0]] * 12),
    ]
    summary: dict = {}
    files = write_figures(
        curves, ["skirmish/bane_no_z", "skirmish/bane_vs_bane"], tmp_path, summary
    )
    kinds = ("median", "variance", "p75", "p25", "final", "final_vs_zerglings")
    assert files == [f"redundancy_{k}.png" for k in kinds]
    for f in files:
        assert (tmp_path / f).stat().st_size > 10_000
    red = summary["redundancy"]
    assert red["zerglings"] == {"skirmish/bane_vs_bane": 20, "skirmish/bane_no_z": 0}
    cell = red["curves"]["skirmish/bane_vs_bane"]["rdn"]
    assert cell["median"][-1] == pytest.approx(0.375)
    assert cell["variance"][-1] == pytest.approx(np.var([0.0, 0.25, 0.5, 0.75]), abs=1e-4)
    assert cell["p75"][-1] == pytest.approx(0.5625) and cell["p25"][-1] == pytest.approx(0.1875)
    assert cell["median"][0] == 0.0 and cell["seeds"] == 4
    final = red["final"]["rdn"]
    assert final["zerglings"] == [20, 0]  # most zerglings first
    assert final["median"] == [pytest.approx(0.375), 1.0]
    assert final["per_seed"][0] == [0.0, 0.25, 0.5, 0.75]
    assert red["final"]["vdn"]["p25"] == [0.5] and red["final"]["vdn"]["p75"] == [1.0]


def test_final_stats_use_the_last_ten_evaluations():
    won = [[1.0, 1.0]] * 5 + [[0.0, 0.5]] * 10
    curves = [_curve("iql", g, won) for g in ("skirmish/bane_small", "skirmish/bane_z5")]
    got = final_stats(curves, ["skirmish/bane_small", "skirmish/bane_z5"])
    assert got["iql"]["per_seed"] == [[0.0, 0.5]] * 2 and got["iql"]["zerglings"] == [10, 5]
    assert got["iql"]["generated"] == [False, True]  # drawn apart from Table 5.1's maps
    # returns the same way: seed 0 returns 4 then 10, seed 1 always 6
    rets = [[4.0, 6.0]] * 5 + [[10.0, 6.0]] * 10
    c = Curve("vdn", "skirmish/bane_med", [1000 * (i + 1) for i in range(15)], won, rets, 1.0)
    got = final_stats([c], ["skirmish/bane_med"])["vdn"]
    assert got["return_per_seed"] == [[10.0, 6.0]] and got["return_median"] == [8.0]
    assert got["return_p25"] == [7.0] and got["return_p75"] == [9.0]


def test_summarise_only_with_t_max_cuts_every_pair_at_one_budget(tmp_path):
    # a 100k-step log every 10k and a 40k-step log every 5k, summarised at 40k steps
    evals = tmp_path / "evals"
    evals.mkdir()
    logs = {
        "skirmish-bane_small__vdn": [
            (t, 1.0 if t > 40_500 else 0.0) for t in range(500, 100_501, 10_000)
        ],
        "skirmish-bane_med__vdn": [(t, 0.5) for t in range(400, 40_401, 5_000)],
    }
    for name, rows in logs.items():
        lines = [
            json.dumps({"t_env": t, "won": [w, w], "returns": [w, w], "wall_s": t / 100})
            for t, w in rows
        ]
        (evals / f"{name}.jsonl").write_text("\n".join(lines) + "\n")
    argv = ["repro", "redundancy", "--envs", "skirmish/bane_small,skirmish/bane_med"]
    argv += ["--algos", "vdn", "--out", str(tmp_path), "--summarise-only", "--bootstrap-reps", "20"]
    assert main([*argv, "--t-max", "40000"]) == 0
    cut = json.loads((tmp_path / "summary.json").read_text())
    small = cut["skirmish/bane_small"]["vdn"]
    assert small["t_env"] == 40_500 and small["wall_s"] == 405.0  # first evaluation past 40k
    assert small["median_win_rate_last10"] == 0.0  # the wins after 40.5k are cut off
    assert cut["skirmish/bane_med"]["vdn"]["t_env"] == 40_400  # shorter than the cut: all of it
    assert cut["redundancy"]["curves"]["skirmish/bane_small"]["vdn"]["t_env"][-1] == 40_500
    assert main(argv) == 0
    whole = json.loads((tmp_path / "summary.json").read_text())["skirmish/bane_small"]["vdn"]
    assert whole["t_env"] == 100_500 and whole["median_win_rate_last10"] == 0.6


@pytest.mark.parametrize("bad", ["x", "5,-1", "65"])
def test_bad_zerglings_exit_2(bad, capsys, tmp_path):
    assert main(["repro", "redundancy", "--zerglings", bad, "--out", str(tmp_path)]) == 2
    assert "--zerglings takes whole numbers" in capsys.readouterr().err


@pytest.mark.slow
def test_tiny_redundancy_run_writes_every_figure_summary_and_checkpoints(tmp_path):
    out = tmp_path / "red"
    argv = ["repro", "redundancy", "--envs", "skirmish/bane_no_z", "--zerglings", "1"]
    argv += ["--algos", "vdn,rdn", "--seeds", "2", "--t-max", "300", "--test-interval", "150"]
    argv += ["--workers", "1", "--set", "run.test_episodes=2", "--set", "replay.batch_size=4"]
    assert main([*argv, "--checkpoints", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["skirmish/bane_z1"]) == {"vdn", "rdn"}
    red = summary["redundancy"]
    assert list(red["curves"]) == ["skirmish/bane_z1", "skirmish/bane_no_z"]
    assert red["final"]["rdn"]["zerglings"] == [1, 0]
    kinds = ("median", "variance", "p75", "p25", "final", "final_vs_zerglings")
    for name in (*kinds, "bane_z1", "bane_no_z"):
        assert (out / f"redundancy_{name}.png").stat().st_size > 0
    assert (out / "checkpoints" / "skirmish-bane_z1__rdn" / "learner.pt").exists()
    assert not (out / "checkpoints" / "skirmish-bane_z1__rdn" / "buffer").exists()  # no replay
    rows = [json.loads(x) for x in (out / "evals" / "skirmish-bane_z1__rdn.jsonl").open()]
    assert all(len(r["won"]) == 2 for r in rows)


def _zero_curve(algo: str, seeds: int) -> Curve:
    return Curve(
        algo, "skirmish/bane_small", [0, 10], [[0.0] * seeds] * 2, [[0.0] * seeds] * 2, 1.0
    )


def test_figure_heading_names_each_algos_seeds_when_they_differ():
    same = headings([_zero_curve("qmix", 3), _zero_curve("rdn", 3)], "skirmish/bane_small")
    assert same == (
        "skirmish/bane_small: median of 3 seeds, 25-75 percentile band",
        {"qmix": "qmix", "rdn": "rdn"},
    )
    title, labels = headings([_zero_curve("qmix", 3), _zero_curve("rdn", 2)], "skirmish/bane_small")
    assert "median of each algo's seeds" in title and "3 seeds" not in title
    assert labels == {"qmix": "qmix (3 seeds)", "rdn": "rdn (2 seeds)"}


def test_a_figure_leaves_out_the_diagnostics_no_algo_logged():
    from cluster.repro.smac import DIAGNOSTICS

    value = [{"q_taken_mean": 1.0, "loss_td": 0.5}, {"q_taken_mean": 2.0}]
    qmix = dataclasses.replace(_zero_curve("qmix", 3), learner=value)
    assert [k for k, _ in logged([qmix], DIAGNOSTICS)] == ["q_taken_mean", "loss_td"]
    critic = [{"q_tot_mean": 1.0, "loss_critic": 0.1}, {}]
    rdn = dataclasses.replace(_zero_curve("rdn", 3), learner=critic)
    assert logged([qmix, rdn], DIAGNOSTICS) == DIAGNOSTICS

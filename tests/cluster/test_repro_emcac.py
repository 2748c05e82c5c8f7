"""`credit repro emcac`: the summary numbers by hand, and a tiny end-to-end run."""

import json

import pytest

from cluster.cli import main
from cluster.repro.curves import summarise_curve


@pytest.mark.parametrize(
    "t_env, won, expected",
    [
        # Median curve [0, .5, .8]: 50% at 20, 80% at 30. Seed means over the (only 3) last
        # evaluations: [1.4/3, 1.2/3, 1.7/3] -> median 1.4/3, mean 4.3/9.
        (
            [10, 20, 30],
            [[0.0, 0.0, 0.2], [0.5, 0.4, 0.9], [0.9, 0.8, 0.6]],
            {
                "median_win_rate_last10": 1.4 / 3,
                "mean_win_rate_last10": 4.3 / 9,
                "steps_to_50": 20,
                "steps_to_80": 30,
                "steps_to_50_smoothed": None,  # fewer evaluations than the window
                "steps_to_80_smoothed": None,
                "steps_to_95": None,
                "steps_to_95_smoothed": None,
                "seeds": 3,
            },
        ),
        # 12 evaluations of one seed: only the last 10 count. Two early wins reach 80% on the
        # raw curve; the first window of 5 is (1 + 1 + 3 x 0.5) / 5 = 0.7 at t=5, so smoothed
        # it reaches 50% there and never 80%.
        (
            list(range(1, 13)),
            [[1.0], [1.0]] + [[0.5]] * 10,
            {
                "median_win_rate_last10": 0.5,
                "mean_win_rate_last10": 0.5,
                "steps_to_50": 1,
                "steps_to_80": 1,
                "steps_to_50_smoothed": 5,
                "steps_to_80_smoothed": None,
                "steps_to_95": 1,
                "steps_to_95_smoothed": None,
                "seeds": 1,
            },
        ),
        # A lucky 0.9 at t=20 is the raw 80%. Windows: (0 + .9 + .6 + .8 + .8) / 5 = 0.62 at
        # t=50, (.9 + .6 + .8 + .8 + 1) / 5 = 0.82 at t=60.
        (
            [10, 20, 30, 40, 50, 60],
            [[0.0], [0.9], [0.6], [0.8], [0.8], [1.0]],
            {
                "median_win_rate_last10": 4.1 / 6,
                "mean_win_rate_last10": 4.1 / 6,
                "steps_to_50": 20,
                "steps_to_80": 20,
                "steps_to_50_smoothed": 50,
                "steps_to_80_smoothed": 60,
                "steps_to_95": 60,
                "steps_to_95_smoothed": None,
                "seeds": 1,
            },
        ),
        (
            [5, 10],
            [[0.1, 0.9], [0.2, 0.3]],
            {
                "median_win_rate_last10": 0.375,
                "mean_win_rate_last10": 0.375,
                "steps_to_50": 5,
                "steps_to_80": None,
                "steps_to_50_smoothed": None,
                "steps_to_80_smoothed": None,
                "steps_to_95": None,
                "steps_to_95_smoothed": None,
                "seeds": 2,
            },
        ),
    ],
)
def test_summary_numbers_by_hand(t_env, won, expected):
    got = summarise_curve(t_env, won)
    assert got.keys() == expected.keys()
    for k, v in expected.items():
        assert got[k] == (pytest.approx(v) if isinstance(v, float) else v), k


def test_tiny_ablation_writes_summary_runs_and_plots(tmp_path, capsys):
    out = tmp_path / "abl"
    code = main(
        [
            "repro",
            "emcac",
            "--envs",
            "skirmish/3m",
            "--algos",
            "cac,emcac",
            "--seeds",
            "2",
            "--t-max",
            "400",
            "--out",
            str(out),
            "--workers",
            "1",
            "--set",
            "run.test_interval=200",
            "--set",
            "run.test_episodes=2",
            "--set",
            "cycling.capacity=8",
            "--set",
            "replay.batch_size=4",
            "--bootstrap-reps",
            "50",
        ]
    )
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary) == {"skirmish/3m", "aggregate", "table52"}
    # 3m is not one of Table 5.2's maps: every cell not run, every claim missing
    assert all(v is None for row in summary["table52"]["cells"].values() for v in row.values())
    assert {c["verdict"] for c in summary["table52"]["claims"]} == {"missing"}
    assert "— not run (vs 62/65)" in (out / "table52.md").read_text()
    assert set(summary["skirmish/3m"]) == {"cac", "emcac"}
    poi = summary["aggregate"]["metrics"]["win_rate"]["probability_of_improvement"]
    assert list(poi) == ["cac > emcac"] and 0.0 <= poi["cac > emcac"]["p"] <= 1.0
    assert (out / "report.html").stat().st_size > 0
    for cell in summary["skirmish/3m"].values():
        assert 0.0 <= cell["median_win_rate_last10"] <= 1.0
        assert 0.0 <= cell["mean_win_rate_last10"] <= 1.0
        assert cell["seeds"] == 2
        for k in ("steps_to_50", "steps_to_80", "steps_to_50_smoothed", "steps_to_80_smoothed"):
            assert cell[k] is None or isinstance(cell[k], int)
    assert (out / "emcac_3m.png").stat().st_size > 0
    lines = [json.loads(x) for x in (out / "evals" / "skirmish-3m__emcac.jsonl").open()]
    assert len(lines) >= 2 and all(len(x["won"]) == 2 for x in lines)
    assert "kl_masked_fraction" in lines[-1]
    assert "skirmish/3m" in capsys.readouterr().out
    # The same summary comes back from the evaluation logs alone.
    before = (out / "summary.json").read_text()
    (out / "summary.json").unlink()
    args = ["repro", "emcac", "--envs", "skirmish/3m", "--algos", "cac,emcac", "--out", str(out)]
    assert main([*args, "--summarise-only", "--bootstrap-reps", "50"]) == 0
    again = json.loads((out / "summary.json").read_text())
    for algo, cell in json.loads(before)["skirmish/3m"].items():
        for k, v in cell.items():
            if k != "wall_s":
                assert again["skirmish/3m"][algo][k] == v, (algo, k)
    assert again["aggregate"] == json.loads(before)["aggregate"]  # seeded: the same draws
    assert again["table52"] == json.loads(before)["table52"]


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--algos", "cac,dqn"], "unknown algorithm 'dqn'"),
        (["--envs", "skirmish/nope"], "unknown env"),
        (["--seeds", "0"], "--seeds must be >= 1"),
        (["--envs", "skirmish/3s5z,smac/3s5z"], "skirmish/3s5z and smac/3s5z are both 3s5z"),
    ],
)
def test_bad_input_exits_2(tmp_path, capsys, argv, message):
    code = main(["repro", "emcac", "--out", str(tmp_path), "--envs", "skirmish/3m", *argv])
    assert code == 2
    assert message in capsys.readouterr().err

"""`credit bench open-loop`: open-loop sequences tuned on one seed, played on held-out seeds
(results/skirmish/README.md, "Open-loop policies")."""

import json
from pathlib import Path

import pytest

from cluster.cli import main

COMMITTED = Path(__file__).resolve().parents[2] / "results" / "skirmish" / "open_loop.json"


def _run(tmp_path: Path, *argv: str) -> dict:
    out = tmp_path / "o" / "open_loop.json"
    assert main(["bench", "open-loop", *argv, "--out", str(out)]) == 0
    return json.loads(out.read_text())


def test_a_tiny_run_reports_every_map_and_tuning_seed(tmp_path, capsys):
    argv = ["--maps", "3m", "--tune-seeds", "0", "1", "--candidates", "2", "--rounds", "1"]
    got = _run(tmp_path, *argv, "--tune-episodes", "1", "--episodes", "4")
    assert json.loads(capsys.readouterr().out) == got  # printed and written alike
    assert got["benchmark"] == "open_loop" and got["held_out_seeds"] == [1000, 1003]
    (m,) = got["maps"]
    assert m["map"] == "3m" and m["randomised"] is False
    assert [r["tune_seed"] for r in m["per_tune_seed"]] == [0, 1]
    for r in m["per_tune_seed"]:
        assert r["open_loop_win_rate"] in (0.0, 0.25, 0.5, 0.75, 1.0)  # of 4 episodes
        assert 0 <= r["best_random_candidate_wins"] <= r["tuned_wins"] <= 1
    rates = [r["open_loop_win_rate"] for r in m["per_tune_seed"]]
    assert m["open_loop_win_rate_mean"] == pytest.approx(sum(rates) / 2)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--maps", "3m", "nope"], "unknown env 'skirmish/nope'"),
        (["--episodes", "0"], "--episodes"),
    ],
)
def test_bad_arguments_exit_2(tmp_path, capsys, argv, message):
    assert main(["bench", "open-loop", *argv, "--out", str(tmp_path / "x.json")]) == 2
    assert message in capsys.readouterr().err


def test_the_committed_3m_row_is_reproduced(tmp_path):
    """3m, tuning seed 0, the committed settings: the numbers of results/skirmish/open_loop.json."""
    committed = next(m for m in json.loads(COMMITTED.read_text())["maps"] if m["map"] == "3m")
    got = _run(tmp_path, "--maps", "3m", "--tune-seeds", "0")["maps"][0]
    assert got["per_tune_seed"][0] == committed["per_tune_seed"][0]
    assert got["focus_fire_closed_loop_win_rate"] == committed["focus_fire_closed_loop_win_rate"]

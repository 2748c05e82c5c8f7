"""`credit env scripted`: scripted and random team win rates on skirmish maps, as JSON."""

import json

import pytest

from cluster.cli import main


def run(capsys, *argv: str) -> dict:
    assert main(["env", "scripted", *argv]) == 0
    return json.loads(capsys.readouterr().out)


def test_focus_fire_beats_random_on_3m_and_the_counts_add_up(capsys, tmp_path):
    out = tmp_path / "ladder.json"
    rec = run(capsys, "--maps", "3m", "--policy", "focus_fire", "random", "--episodes", "30",
              "--seeds", "0", "1", "--out", str(out))  # fmt: skip
    assert rec["benchmark"] == "env_scripted" and "command" in rec and "machine" in rec
    assert json.loads(out.read_text()) == rec
    rows = {r["policy"]: r for r in rec["results"]}
    assert set(rows) == {"focus_fire", "random"}
    for r in rows.values():
        assert r["map"] == "3m" and r["settings"] == {} and r["episodes"] == 60
        assert [s["seed"] for s in r["per_seed"]] == [0, 1]
        assert all(s["episodes"] == 30 for s in r["per_seed"])
        assert r["wins"] == round(r["win_rate"] * 60)
    assert rows["focus_fire"]["win_rate"] >= 0.6
    assert rows["random"]["win_rate"] <= 0.1


def test_same_seeds_give_the_same_rows(capsys):
    args = ("--maps", "bane_small", "--policy", "bane_charge", "--episodes", "20", "--seeds", "3")
    assert run(capsys, *args)["results"] == run(capsys, *args)["results"]


def test_default_policies_follow_the_map(capsys):
    rec = run(capsys, "--maps", "bane_z5", "8m", "--episodes", "2", "--seeds", "0")
    got = [(r["map"], r["policy"]) for r in rec["results"]]
    assert got == [("bane_z5", "bane_charge"), ("bane_z5", "nearest"), ("bane_z5", "random"),
                   ("8m", "focus_fire"), ("8m", "nearest"), ("8m", "random")]  # fmt: skip


def test_sweep_and_set_reach_the_simulator(capsys):
    # Without splash avoidance the attack-move enemy balls up and a random team's banelings
    # wipe it; with it the random team loses: the option must reach the simulator.
    sweep = ("--set", "acquire_range=9", "--sweep", "bane_dodge=-1,0.5")
    rec = run(capsys, "--maps", "bane_vs_bane", "--policy", "random", "--episodes", "40",
              "--seeds", "0", *sweep)  # fmt: skip
    rows = rec["results"]
    assert [r["settings"] for r in rows] == [
        {"acquire_range": 9, "bane_dodge": -1},
        {"acquire_range": 9, "bane_dodge": 0.5},
    ]
    assert rows[0]["win_rate"] >= rows[1]["win_rate"] + 0.3


@pytest.mark.parametrize(
    ("argv", "named"),
    [
        (["--maps", "bane_nope"], "bane_nope"),
        (["--maps", "bane_z99"], "0..64"),
        (["--policy", "charge_everything"], "charge_everything"),
        (["--set", "bane_dodge=far"], "bane_dodge"),
        (["--set", "no_such_option=1"], "no_such_option"),
        (["--set", "bane_dodge"], "key=value"),
        (["--sweep", "bane_dodge"], "KEY=V1,V2"),
        (["--sweep", "bane_dodge=0.5,oops"], "bane_dodge"),
        (["--episodes", "0"], "--episodes"),
        (["--num-envs", "0"], "--num-envs"),
    ],
)
def test_bad_input_is_named_and_exits_2(capsys, argv, named):
    assert main(["env", "scripted", "--maps", "3m", "--episodes", "2", *argv]) == 2
    captured = capsys.readouterr()
    assert named in captured.err and captured.out == ""


def test_a_map_file_plays_like_a_built_in_map(capsys, tmp_path):
    path = tmp_path / "blob_3m.yml"
    path.write_text(
        "episode_limit: 60\nformation: blob\n"
        "allies: [{type: marine, count: 3, at: [9, 16]}]\n"
        "enemies: [{type: marine, count: 3, at: [23, 16]}]\n"
    )
    rec = run(capsys, "--maps", str(path), "--episodes", "10", "--seeds", "0")
    assert [r["policy"] for r in rec["results"]] == ["focus_fire", "nearest", "random"]
    assert all(r["map"] == str(path) and r["episodes"] == 10 for r in rec["results"])
    missing = tmp_path / "nowhere.yaml"
    assert main(["env", "scripted", "--maps", str(missing), "--episodes", "2"]) == 2
    assert "nowhere.yaml" in capsys.readouterr().err

"""Seed groups (`--seed-group G`, cluster.repro.groups): a pair's seeds split over runs into
one --out keep their own files and random streams, and the summary merges them into one
curve."""

from __future__ import annotations

import json
import logging
import random
from dataclasses import replace

import pytest
import torch

from cluster.cli import main
from cluster.config.train import load_train_config
from cluster.errors import UsageError
from cluster.launch.local import LocalTrainer
from cluster.process import configure
from cluster.repro import curves, groups, matrix

SKIRMISH = ["--envs", "skirmish/3m", "--algos", "vdn", "--t-max", "120", "--workers", "1"]
SKIRMISH += ["--test-interval", "40", "--checkpoint-every", "60"]
for _s in ("run.num_envs=2", "run.test_episodes=2", "replay.batch_size=4"):
    SKIRMISH += ["--set", _s]


def _disjoint(a: dict[str, range], b: dict[str, range]) -> bool:
    return all(not set(a[k]) & set(b[k]) for k in a)


def test_groups_never_share_a_seed_and_a_group_too_large_is_refused():
    run = load_train_config("vdn", "skirmish/3m", [], []).run
    kw = {"num_envs": run.num_envs, "test_episodes": run.test_episodes}
    # run.seed = G would not do: group 1's envs would be group 0's envs 1, 2, ...
    assert not _disjoint(groups.streams(0, 3, **kw), groups.streams(1, 3, **kw))
    for a, b, members in ((0, 1, (3, 3)), (0, 1, (1, 2)), (1, 7, (8, 2))):
        groups.check(a, 0, members[0], **kw)
        groups.check(b, 0, members[1], **kw)
        sa = groups.streams(groups.group_seed(a), members[0], **kw)
        assert _disjoint(sa, groups.streams(groups.group_seed(b), members[1], **kw))
    with pytest.raises(UsageError, match="evaluation envs would be seeded"):
        groups.check(1, 0, 5000, **kw)  # 5000 * 20 evaluation envs overrun the window
    with pytest.raises(UsageError, match=r"run\.seed 100000 must be"):
        groups.check(1, groups.STRIDE, 1, **kw)


def test_the_seeds_named_are_the_seeds_the_trainer_uses():
    """`groups.streams` describes cluster/process.py, cluster/evaluation.py and
    cluster/launch/local.py: checked on a real seed-batched trainer, so that a change there
    cannot quietly let groups overlap."""
    seed = groups.group_seed(2)
    cfg = load_train_config(
        "vdn", "skirmish/3m", [], [f"run.seed={seed}", "run.num_envs=2", "run.torch_threads=1"]
    )
    configure(cfg.run)  # as every training entry point does (a repro pair included)
    trainer = LocalTrainer(cfg, n_ensemble=2)
    want = groups.streams(seed, 2, cfg.run.num_envs, cfg.run.test_episodes)
    assert torch.initial_seed() == seed
    evaluator = trainer.core.evaluator
    workers = [trainer.worker.gen.initial_seed(), evaluator.worker.gen.initial_seed()]
    assert workers == list(want["torch generators"])
    for venv, kind in ((trainer.worker.venv, "training envs"), (evaluator.venv, "evaluation envs")):
        assert [g.bit_generator.seed_seq.entropy for g in venv.rngs] == list(want[kind])
    tables = [random.Random(s).getstate() for s in want["replay tables"]]
    assert [b.rng.getstate() for b in trainer.data.buffers] == tables


def _rows(t_env: list[int], seeds: int, value: float) -> list[dict]:
    return [
        {
            "t_env": t,
            "won": [value] * seeds,
            "returns": [value] * seeds,
            "wall_s": t / 10,
            "loss_td": value,
            "commit": f"c{seeds}",
        }
        for t in t_env
    ]


def test_merge_concatenates_seeds_up_to_the_shortest_group(caplog):
    g0, g1 = _rows([10, 52, 101], 1, 0.0), _rows([12, 49], 2, 1.0)
    with caplog.at_level(logging.WARNING):
        rows, info = groups.merge({0: g0, 1: g1}, "vdn@x")
    assert "summarised up to the shortest, group 1's (2 evaluations, to t_env 49)" in caplog.text
    assert [r["t_env"] for r in rows] == [12, 52]
    assert rows[0]["won"] == [0.0, 1.0, 1.0] and rows[1]["wall_s"] == 5.2
    assert rows[0]["loss_td"] == pytest.approx(2 / 3)  # weighted by seeds
    assert info["groups"] == [
        {"group": 0, "seeds": 1, "evaluations": 3},
        {"group": 1, "seeds": 2, "evaluations": 2},
    ]
    assert info["commits"] == ["c1", "c2"]
    with pytest.raises(UsageError, match="different --test-interval"):
        groups.merge({0: g0, 1: _rows([100, 200], 1, 1.0)}, "vdn@x")


def _write(folder, name: str, rows: list[dict]) -> None:
    (folder / name).write_text("".join(json.dumps(r) + "\n" for r in rows))


def test_a_group_still_training_is_left_out_of_another_groups_summary(tmp_path, caplog):
    """A run of group 0 that ends while group 1 still trains into the same --out summarises
    the finished groups only (it used to cut them all to group 1's few evaluations)."""
    _write(tmp_path, "skirmish-3m__vdn.jsonl", _rows([10, 52, 101], 1, 0.0))
    _write(tmp_path, "skirmish-3m__vdn.g1.jsonl", _rows([12, 49], 2, 1.0))  # still training
    _write(tmp_path, "skirmish-3m__vdn.g2.jsonl", _rows([11, 50, 100], 1, 1.0))
    _write(tmp_path, "matrix-two_step__vdn.jsonl", _rows([10, 52, 101], 1, 0.0))
    _write(tmp_path, "matrix-two_step__vdn.g1.jsonl", _rows([12, 49], 2, 1.0))
    mine = curves.load_pair(tmp_path, "vdn", "skirmish/3m", finished_at=999)
    assert mine is None  # no group has finished a run of 999 steps
    own = curves.curve_of("vdn", "skirmish/3m", _rows([10, 52, 101], 1, 0.0))
    own = replace(own, groups=[{"group": 0, "seeds": 1, "evaluations": 3}])
    with caplog.at_level(logging.WARNING):
        (merged,) = curves.with_other_groups([own], tmp_path, {("skirmish/3m", "vdn"): 100})
    assert "vdn@skirmish/3m: seed group 1's log ends at t_env 49 of 100" in caplog.text
    assert [g["group"] for g in merged.groups] == [0, 2]
    assert merged.t_env == [11, 52, 101] and merged.won[-1] == [0.0, 1.0]
    (alone,) = curves.with_other_groups([own], tmp_path, {("skirmish/3m", "vdn"): 101})
    assert alone is own  # group 2 (to 100) has not finished a run of 101 either
    game = matrix.load_pair(tmp_path, "vdn", "matrix/two_step")
    assert game is not None and len(game.t_env) == 2  # --summarise-only: up to the shortest
    mine = replace(game, groups=[{"group": 0, "seeds": 1, "evaluations": 3}])
    (kept,) = matrix.with_other_groups([mine], tmp_path, {("matrix/two_step", "vdn"): 100})
    assert kept is mine


def _log(out, name: str) -> list[dict]:
    return [json.loads(x) for x in (out / "evals" / name).read_text().splitlines()]


@pytest.mark.slow  # about 25 s at load 4 (two cores busy): three tiny skirmish runs
def test_two_seed_groups_of_a_pair_make_one_summary(tmp_path, capsys, caplog):
    out = tmp_path / "out"
    base = ["repro", "smac", *SKIRMISH, "--out", str(out)]
    assert main([*base, "--seeds", "1"]) == 0
    assert main([*base, "--seeds", "2", "--seed-group", "1"]) == 0
    g0, g1 = _log(out, "skirmish-3m__vdn.jsonl"), _log(out, "skirmish-3m__vdn.g1.jsonl")
    assert len(g0[0]["returns"]) == 1 and len(g1[0]["returns"]) == 2
    mine = [r["returns"][0] for r in g0]
    for m in range(2):  # each seed of group 1 plays its own games
        assert [r["returns"][m] for r in g1][: len(mine)] != mine[: len(g1)]
    records = sorted(p.name for p in (out / "pairs").iterdir())
    assert records == ["skirmish-3m__vdn.g1.json", "skirmish-3m__vdn.json"]
    trained = json.loads((out / "summary.json").read_text())["skirmish/3m"]["vdn"]
    assert trained["seeds"] == 3  # the second command's summary merges group 0 in
    assert main([*base, "--summarise-only"]) == 0
    cell = json.loads((out / "summary.json").read_text())["skirmish/3m"]["vdn"]
    assert cell["seeds"] == 3 and [g["group"] for g in cell["groups"]] == [0, 1]
    assert [g["seeds"] for g in cell["groups"]] == [1, 2] and cell["commits"]
    assert cell["median_win_rate_last10"] == trained["median_win_rate_last10"]
    # a rerun of group 1 is finished already; group 0's log is not touched
    before = (out / "evals" / "skirmish-3m__vdn.jsonl").stat().st_mtime_ns
    caplog.set_level(logging.INFO)
    assert main([*base, "--seeds", "2", "--seed-group", "1"]) == 0
    assert "vdn@skirmish/3m (seed group 1) finished in an earlier run" in caplog.text
    assert (out / "evals" / "skirmish-3m__vdn.jsonl").stat().st_mtime_ns == before
    assert _log(out, "skirmish-3m__vdn.g1.jsonl") == g1


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--seed-group", "-1"], "--seed-group must be 0..999, got -1"),
        (["--seed-group", "1000"], "--seed-group must be 0..999, got 1000"),
        (["--seed-group", "1", "--summarise-only"], "drop --seed-group"),
        (["--seed-group", "1", "--seeds", "50000"], "use fewer seeds per group"),
        (["--seed-group", "1", "--set", "run.seed=100000"], "run.seed 100000 must be"),
    ],
)
def test_bad_seed_groups_exit_2(tmp_path, capsys, extra, message):
    argv = ["repro", "smac", *SKIRMISH, "--out", str(tmp_path / "o"), *extra]
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_matrix_groups_merge_in_the_summary_and_a_finished_group_is_skipped(tmp_path, caplog):
    argv = ["repro", "matrix", "--algos", "vdn", "--games", "matrix/two_step", "--t-max", "60"]
    argv += ["--workers", "1", "--set", "run.test_interval=20", "--bootstrap-reps", "10"]
    argv += ["--out", str(tmp_path)]
    assert main([*argv, "--seeds", "1"]) == 0
    assert main([*argv, "--seeds", "2", "--seed-group", "3"]) == 0
    cell = json.loads((tmp_path / "summary.json").read_text())["vdn"]["two_step"]
    assert cell["runs"] == 3 and [g["group"] for g in cell["groups"]] == [0, 3]
    assert (tmp_path / "pairs" / "matrix-two_step__vdn.g3.json").exists()
    logs = {p.name: p.read_text() for p in (tmp_path / "evals").iterdir()}
    assert sorted(logs) == ["matrix-two_step__vdn.g3.jsonl", "matrix-two_step__vdn.jsonl"]
    caplog.set_level(logging.INFO)
    assert main([*argv, "--seeds", "2", "--seed-group", "3"]) == 0
    assert "vdn@matrix/two_step (seed group 3) finished in an earlier run" in caplog.text
    assert {p.name: p.read_text() for p in (tmp_path / "evals").iterdir()} == logs

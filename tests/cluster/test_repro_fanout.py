"""`credit repro ... --address`: the run options of every repro command, the clear error for a
cluster that is not there, and the driver's collector and local pool (cluster.repro.fanout).
The runs on a real multi-process Ray cluster are in test_repro_cluster.py (slow tier)."""

from __future__ import annotations

import json
import socket

import pytest

from cluster.cli import build_parser, main
from cluster.repro.fanout import run_pairs
from cluster.repro.options import fan_out_config
from cluster.repro.pairs import Collector, FanOutConfig, Pair, PairEvent, StatusLine

COMMANDS = {
    "matrix": ["repro", "matrix", "--out", "OUT"],
    "emcac": ["repro", "emcac", "--out", "OUT"],
    "smac": ["repro", "smac", "--out", "OUT"],
    "redundancy": ["repro", "redundancy", "--out", "OUT"],
}


def _closed_port() -> int:
    """A loopback port nobody listens at (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_repro_command_takes_the_cluster_options(command):
    parser = build_parser()
    default = fan_out_config(parser.parse_args(COMMANDS[command]))
    assert default == FanOutConfig(workers=2, address=None, cpus_per_pair=1.0, max_retries=3)
    assert default.ship_code
    argv = [*COMMANDS[command], "--address", "10.0.0.5:6379", "--cpus-per-pair", "2.5"]
    argv += ["--max-retries", "0", "--no-ship-code", "--workers", "1"]
    got = fan_out_config(parser.parse_args(argv))
    assert got == FanOutConfig(
        workers=1, address="10.0.0.5:6379", cpus_per_pair=2.5, max_retries=0, ship_code=False
    )
    auto = fan_out_config(parser.parse_args([*COMMANDS[command], "--address", "auto"]))
    assert auto.address == "auto"


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--cpus-per-pair", "0"], "--cpus-per-pair must be > 0"),
        (["--max-retries", "-1"], "--max-retries must be >= 0"),
        (["--workers", "0"], "--workers must be >= 1"),
        (["--address", "nohost"], "--address takes 'auto' or HOST:PORT"),
    ],
)
def test_bad_cluster_options_exit_2(tmp_path, capsys, argv, message):
    base = ["repro", "matrix", "--algos", "vdn", "--games", "matrix/two_step", "--t-max", "40"]
    assert main([*base, "--out", str(tmp_path), *argv]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("command", ["matrix", "smac"])
def test_unreachable_address_names_it_and_how_to_start_a_cluster(tmp_path, capsys, command):
    address = f"127.0.0.1:{_closed_port()}"
    if command == "matrix":
        argv = ["repro", "matrix", "--algos", "vdn", "--games", "matrix/two_step"]
    else:
        argv = ["repro", "smac", "--algos", "vdn", "--envs", "skirmish/3m"]
    code = main([*argv, "--t-max", "40", "--out", str(tmp_path / "o"), "--address", address])
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"no Ray cluster answers at {address}" in err and "credit cluster up" in err
    assert "Traceback" not in err
    assert not list((tmp_path / "o" / "evals").glob("*.jsonl"))  # nothing ran


def test_auto_with_a_recorded_cluster_that_is_gone(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("CREDIT_STATE_DIR", str(tmp_path / "state"))
    (tmp_path / "state" / "cluster").mkdir(parents=True)
    gone = f"127.0.0.1:{_closed_port()}"
    state = {"address": gone, "num_cpus": 2, "pgid": None}
    (tmp_path / "state" / "cluster" / "state.json").write_text(json.dumps(state))
    argv = ["repro", "emcac", "--algos", "cac", "--envs", "skirmish/3m", "--t-max", "40"]
    assert main([*argv, "--out", str(tmp_path / "o"), "--address", "auto"]) == 2
    err = capsys.readouterr().err
    assert "--address auto: the cluster recorded in" in err and gone in err
    assert "credit cluster up" in err and "Traceback" not in err


def _lines(path):
    return path.read_text().splitlines()


def test_collector_restarts_a_log_and_drops_a_lost_attempts_lines(tmp_path, caplog):
    pair = Pair("vdn", "matrix/two_step")
    c = Collector([pair], tmp_path)
    log = tmp_path / "matrix-two_step__vdn.jsonl"
    first, second = "h:11:1", "h:12:2"
    c.handle(PairEvent(pair, "started", first))
    c.handle(PairEvent(pair, "evaluated", first, '{"t_env": 2}'))
    c.handle(PairEvent(pair, "evaluated", first, '{"t_env": 22}\n'))
    assert _lines(log) == ['{"t_env": 2}', '{"t_env": 22}']
    with caplog.at_level("INFO", logger="cluster.repro.pairs"):
        c.handle(PairEvent(pair, "started", second))  # the retry of a lost attempt
    assert _lines(log) == []
    assert "pair vdn@matrix/two_step restarted on h (pid 12), attempt 2" in caplog.text
    c.handle(PairEvent(pair, "evaluated", first, '{"t_env": 42}'))  # late, from the dead one
    c.handle(PairEvent(pair, "evaluated", second, '{"t_env": 2}'))
    c.handle(PairEvent(pair, "finished", first, wall_s=9.0))
    assert c.finished == set()
    with caplog.at_level("INFO", logger="cluster.repro.pairs"):
        c.handle(PairEvent(pair, "finished", second, wall_s=3.0))
    assert _lines(log) == ['{"t_env": 2}']
    assert c.finished == {pair}
    assert "pair vdn@matrix/two_step finished in 3 s (1/1 pairs done)" in caplog.text


def test_status_line_counts_each_pairs_latest_evaluation(tmp_path, caplog):
    pairs = [Pair("vdn", "matrix/two_step"), Pair("iql", "matrix/two_step")]
    c = Collector(pairs, None, StatusLine(total_steps=200, key="returns", name="return"))
    c.bar.tty = False  # its log line, also under pytest -s on a terminal
    rows = [(pairs[0], 22, [7.0, 8.0, 8.0]), (pairs[1], 2, [7.0]), (pairs[0], 42, [8.0])]
    for pair in pairs:
        c.handle(PairEvent(pair, "started", f"h:1:{pair.algo}"))
    for pair, t, returns in rows:
        line = json.dumps({"t_env": t, "returns": returns})
        c.handle(PairEvent(pair, "evaluated", f"h:1:{pair.algo}", line))
    with caplog.at_level("INFO", logger="cluster.progress"):
        c.tick()
    assert (
        "t_env 44/200 0/2 pairs done; return vdn@matrix/two_step 8.00, iql@matrix/two_step 7.00"
        in caplog.text
    )


def report_steps(algo: str, env: str, n: int, report=None) -> str:
    """A pair function for the pool tests: n evaluation lines, then its name (module-level,
    so that the pool's worker processes find it)."""
    if algo == "bad":
        raise ValueError("a pair's own error")
    for t in range(n):
        report(json.dumps({"algo": algo, "env": env, "t_env": t}))
    return f"{algo}@{env}"


@pytest.mark.parametrize("workers", [1, 2])
def test_local_pairs_write_their_logs_and_return_in_pair_order(tmp_path, workers):
    pairs = [Pair(a, g) for g in ("m/x", "m/y") for a in ("a", "b")]
    got = run_pairs(report_steps, pairs, (3,), FanOutConfig(workers=workers), tmp_path)
    assert got == ["a@m/x", "b@m/x", "a@m/y", "b@m/y"]
    for p in pairs:
        rows = [json.loads(x) for x in _lines(tmp_path / f"{p.key}.jsonl")]
        assert rows == [{"algo": p.algo, "env": p.env, "t_env": t} for t in range(3)]


def test_a_pairs_own_error_ends_the_local_run(tmp_path):
    pairs = [Pair("a", "m/x"), Pair("bad", "m/x")]
    with pytest.raises(ValueError, match="a pair's own error"):
        run_pairs(report_steps, pairs, (2,), FanOutConfig(workers=2), tmp_path)

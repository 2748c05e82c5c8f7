"""A map file a user wrote, given as an env (`--envs path/to/map.yaml`, `--env path`): it
trains, evaluates and is summarised like a built-in map; a bad file stops the command with
exit code 2 and a message naming the file and the field."""

import json
import textwrap
from pathlib import Path

import pytest

from actors.envs.registry import env_info, make_vec_env
from cluster.cli import main
from cluster.config.shipped import default_files
from cluster.config.train import load_train_config
from cluster.repro.curves import Curve
from cluster.repro.redundancy import ordered, write_figures, zerglings_of

BANE_7Z = """\
name: my_bane
episode_limit: 200
type_order: {allies: [baneling, zergling], enemies: [baneling, zergling]}
unit_type_bits: 2
allies:
  - {type: zergling, count: 7, at: [11, 16]}
  - {type: baneling, count: 4, at: [8, 16]}
enemies:
  - {type: zergling, count: 20, at: [21, 16]}
  - {type: baneling, count: 4, at: [24, 16]}
"""

DRAWN = """\
episode_limit: 60
team_gen: {unit_types: [stalker, zealot], weights: [0.5, 0.5]}
n_units: 3
"""


def _write(folder: Path, name: str, text: str) -> str:
    path = folder / name
    path.write_text(textwrap.dedent(text))
    return str(path)


def _curve(algo: str, env: str, won: float) -> Curve:
    return Curve(
        algo, env, [1000 * (i + 1) for i in range(12)], [[won, won]] * 12, [[1.0] * 2] * 12, 1.0
    )


def test_a_map_file_is_an_env_of_the_skirmish_family(tmp_path):
    path = _write(tmp_path, "my_bane.yaml", BANE_7Z)
    info = env_info(path)
    assert info.n_agents == 11 and info.n_enemies == 24
    venv = make_vec_env(path, 2, seed=0)
    assert venv.num_envs == 2
    venv.close()
    cfg = load_train_config("vdn", path)
    assert cfg.env.id == path
    layers = [p.name for p in default_files("vdn", path)]
    assert layers == ["skirmish.yaml", "vdn.yaml", "skirmish.value.yaml"]  # the family's


def test_the_redundancy_figures_place_a_map_file_by_its_zerglings(tmp_path):
    bane = _write(tmp_path, "my_bane.yaml", BANE_7Z)
    drawn = _write(tmp_path, "drawn.yml", DRAWN)
    assert zerglings_of(bane) == 7 and zerglings_of(drawn) is None
    envs = [drawn, bane, "skirmish/bane_no_z", "skirmish/bane_med"]
    assert ordered(envs) == ["skirmish/bane_med", bane, "skirmish/bane_no_z", drawn]
    curves = [_curve("rdn", g, w) for g, w in zip(envs, (0.1, 0.2, 0.3, 0.4), strict=True)]
    summary: dict = {}
    write_figures(curves, envs, tmp_path, summary)
    red = summary["redundancy"]
    assert red["zerglings"] == {
        "skirmish/bane_med": 15,
        bane: 7,
        "skirmish/bane_no_z": 0,
        drawn: None,
    }
    final = red["final"]["rdn"]
    assert final["env"] == ["skirmish/bane_med", bane, "skirmish/bane_no_z"]  # drawn: off the chart
    assert final["zerglings"] == [15, 7, 0] and final["median"] == [0.4, 0.2, 0.3]
    assert final["map_file"] == [False, True, False] and final["generated"] == [False] * 3
    assert list(red["curves"][drawn]) == ["rdn"]  # still in the per-evaluation figures


BAD = [
    ("missing.yaml", None, "does not exist"),
    ("typo.yaml", BANE_7Z.replace("allies:", "alies:"), "unknown field 'alies'"),
    (
        "unit.yaml",
        BANE_7Z.replace("type: zergling, count: 7", "type: zorgling, count: 7"),
        "zorgling",
    ),
    ("count.yaml", BANE_7Z.replace("count: 7", "count: -7"), "count: must be an int >= 0"),
    ("limit.yaml", BANE_7Z.replace("episode_limit: 200", "episode_limit: 0"), "'episode_limit'"),
    ("broken.yaml", "allies: [", "not valid YAML"),
    ("binary.yaml", "", "cannot be read"),
]


@pytest.mark.parametrize(("name", "text", "message"), BAD, ids=[b[0] for b in BAD])
def test_a_bad_map_file_exits_2_naming_the_file_and_the_field(
    tmp_path, capsys, name, text, message
):
    path = str(tmp_path / name) if text is None else _write(tmp_path, name, text)
    if name == "binary.yaml":
        Path(path).write_bytes(b"\xff\xfe\x00 not text")
    out = tmp_path / "out"
    assert main(["repro", "redundancy", "--envs", path, "--algos", "vdn", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert path in err and message in err, err
    assert not (out / "evals").exists() or not any((out / "evals").iterdir())  # nothing ran
    assert main(["train", "--algo", "vdn", "--env", path, "--out", str(out / "t")]) == 2
    err = capsys.readouterr().err
    assert path in err and message in err, err
    assert not (out / "t").exists()


@pytest.mark.parametrize("env", ["my_bane.yaml", "skirmish/3m"])
def test_a_fixed_map_takes_no_map_argument(tmp_path, capsys, env):
    path = _write(tmp_path, "my_bane.yaml", BANE_7Z)
    env = path if env.endswith(".yaml") else env
    argv = ["train", "--env", env, "--set", f"env.args.map_file={path}", "--t-max", "10"]
    assert main([*argv, "--out", str(tmp_path / "t")]) == 2
    assert "is one fixed map: drop the env argument(s) ['map_file']" in capsys.readouterr().err


def test_skirmish_custom_with_map_file_is_summarised_as_the_map_file(tmp_path):
    path = _write(tmp_path, "my_bane.yaml", BANE_7Z)
    assert zerglings_of("skirmish/custom") == 12  # without map_file: the packaged example
    (tmp_path / "evals").mkdir()
    rows = [
        {"t_env": 100 * k, "won": [0.5, 1.0], "returns": [1.0, 2.0], "wall_s": k} for k in (1, 2)
    ]
    log = tmp_path / "evals" / f"{path.lstrip('/').replace('/', '-')}__vdn.jsonl"
    log.write_text("".join(json.dumps(r) + "\n" for r in rows))
    argv = ["repro", "redundancy", "--envs", "skirmish/custom,skirmish/bane_med", "--algos", "vdn"]
    argv += ["--set", f"env.args.map_file={path}", "--summarise-only", "--out", str(tmp_path)]
    assert main(argv) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary[path]["vdn"]["mean_win_rate_last10"] == 0.75
    assert summary["redundancy"]["zerglings"] == {path: 7}  # bane_med has no log here
    assert (tmp_path / "redundancy_my_bane.png").exists()


def test_on_a_cluster_a_map_file_needs_its_absolute_path(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _write(tmp_path, "my_bane.yaml", BANE_7Z)
    argv = ["repro", "redundancy", "--envs", "my_bane.yaml", "--address", "127.0.0.1:1"]
    assert main([*argv, "--out", "out"]) == 2
    assert "give a map file by its absolute path" in capsys.readouterr().err


def test_two_map_files_of_one_stem_are_refused(tmp_path, capsys):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    paths = [_write(tmp_path / d, "m.yaml", BANE_7Z) for d in ("a", "b")]
    argv = ["repro", "smac", "--envs", ",".join(paths), "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    assert "would share the plot name 'm'" in capsys.readouterr().err


@pytest.mark.slow
def test_tiny_redundancy_run_on_a_map_file(tmp_path):
    path = _write(tmp_path, "my_bane.yaml", BANE_7Z)
    out = tmp_path / "red"
    argv = ["repro", "redundancy", "--envs", f"{path},skirmish/bane_no_z", "--algos", "vdn"]
    argv += ["--seeds", "2", "--t-max", "300", "--test-interval", "150", "--workers", "1"]
    argv += ["--set", "run.test_episodes=2", "--set", "replay.batch_size=4"]
    assert main([*argv, "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    cell = summary[path]["vdn"]
    assert cell["seeds"] == 2 and cell["t_env"] >= 300
    assert 0.0 <= cell["median_win_rate_last10"] <= 1.0
    red = summary["redundancy"]
    assert red["zerglings"] == {path: 7, "skirmish/bane_no_z": 0}
    assert red["names"] == {path: "my_bane", "skirmish/bane_no_z": "bane_no_z"}
    assert red["final"]["vdn"]["zerglings"] == [7, 0]
    for name in ("my_bane", "bane_no_z", "median", "variance", "p75", "p25", "final"):
        assert (out / f"redundancy_{name}.png").stat().st_size > 0
    log = out / "evals" / f"{path.lstrip('/').replace('/', '-')}__vdn.jsonl"
    rows = [json.loads(x) for x in log.open()]
    assert rows[-1]["env"] == path and len(rows[-1]["won"]) == 2
    # the logs rebuild the same summary
    assert main([*argv, "--out", str(out), "--summarise-only"]) == 0
    again = json.loads((out / "summary.json").read_text())
    assert again[path]["vdn"]["median_win_rate_last10"] == cell["median_win_rate_last10"]

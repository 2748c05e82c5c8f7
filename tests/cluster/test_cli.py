"""The command registry: every command module is reachable from `credit`."""

import pkgutil

import cluster.commands
from cluster.cli import COMMANDS, build_parser


def test_every_command_module_is_registered():
    modules = {m.name for m in pkgutil.iter_modules(cluster.commands.__path__)}
    assert modules == set(COMMANDS)


def test_a_command_loads_only_its_own_module():
    # `credit buffer serve` is a long-lived service: it must not carry torch, numba or the
    # envs (358 MB resident when every command was imported for every run)
    import subprocess
    import sys

    code = (
        "import sys; from cluster.cli import build_parser, _command; "
        "build_parser(_command(['-v', 'buffer', 'serve', '--port', '0'])); "
        "print(sorted(m for m in ('torch', 'numba', 'actors.envs', 'ray') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_errors_of_commands_not_loaded_still_exit_with_their_status(capsys):
    from cluster.cli import main

    # an unknown env id raises EnvError from the env registry, loaded by `credit train` itself
    assert main(["train", "--env", "skirmish/no_such_map", "--algo", "qmix", "--t-max", "10"]) == 2
    assert "no_such_map" in capsys.readouterr().err


def test_help_lists_the_commands(capsys):
    parser = build_parser()
    text = parser.format_help()
    for name in (
        "train",
        "repro",
        "cluster",
        "buffer",
        "metrics",
        "dashboard",
        "env",
        "bench",
        "demo",
    ):
        assert name in text


def test_env_list_shows_the_randomised_scenarios(capsys):
    import json

    from cluster.cli import main

    assert main(["env", "list", "--json"]) == 0
    rows = {r["id"]: r for r in json.loads(capsys.readouterr().out)}
    for race in ("protoss", "terran", "zerg"):
        for size in ("5_vs_5", "10_vs_10", "10_vs_11", "20_vs_20"):
            assert rows[f"skirmish/{race}_{size}"]["episode_limit"] == 200
    row = rows["skirmish/protoss_5_vs_5"]
    assert (row["obs_shape"], row["state_shape"], row["n_actions"]) == (92, 130, 11)


def _commands(parser, path=()):
    """(path, help text) of every subcommand below `parser`, depth first."""
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            for name, sub in action.choices.items():
                yield (*path, name), helps[name], sub
                yield from _commands(sub, (*path, name))


def test_top_level_help_is_whole_sentences():
    text = build_parser().description
    assert text.startswith("credit trains") and text.endswith(".")
    assert "`cluster/commands" not in text  # not the module docstring cut in half


def test_every_subcommand_says_in_sentences_what_it_writes():
    found = list(_commands(build_parser()))
    assert len(found) >= 29  # every command and sub-command, bench and repro included
    for path, text, sub in found:
        where = " ".join(path)
        assert text and text[0].isupper() and text.endswith("."), f"credit {where}: {text!r}"
        assert sub.description == text, f"credit {where} --help differs from its list entry"
        says = ("writes", "write ", "writing", "prints", "print ", "lives in", "live in", "remove")
        assert any(w in text.lower() for w in says), f"credit {where}: {text!r}"

"""Config loading: shipped YAML layers, overrides, and errors that name the key."""

import pytest

from cluster.config.schema import ConfigError, parse_overrides, read_yaml
from cluster.config.train import build_train_config, load_train_config


def test_shipped_layers_apply_seed_hyper_parameters():
    cfg = load_train_config("rdn", "matrix/four_game")
    assert cfg.algo.lr == 5e-4 and cfg.algo.gamma == 0.99 and cfg.algo.target_update_episodes == 200
    assert cfg.algo.critic_hidden == (64, 64) and cfg.algo.obs_window == 4
    assert cfg.replay.capacity == 200 and cfg.replay.batch_size == 4
    assert cfg.exploration.epsilon_anneal_time == 2000
    qmix = load_train_config("qmix", "matrix/two_step")
    assert qmix.algo.mixer_embed == 32


def test_overrides_win_and_are_typed():
    cfg = load_train_config(
        "vdn", "matrix/two_step", overrides=["algo.lr=0.001", "run.seed=7", "algo.double_q=false"]
    )
    assert cfg.algo.lr == 0.001 and cfg.run.seed == 7 and cfg.algo.double_q is False
    assert parse_overrides(["a.b=1", "a.c=x"]) == {"a": {"b": 1, "c": "x"}}


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["algo.lrr=0.1"], "unknown config key algo.lrr; valid keys in algo: gamma, lr"),
        (["run.t_max=many"], "run.t_max: expected an integer, got 'many'"),
        (["algo.lr=-1"], "algo: lr must be > 0"),
        (["replay.batch_size=500"], "batch_size=500 exceeds capacity=200"),
        (["algo.agent_targets=magic"], "algo.agent_targets: 'magic' is not one of"),
        (["trainer.x=1"], "unknown config section 'trainer'"),
        (["run.seed"], "--set expects key=value"),
        (["exploration.epsilon_finish=2"], "epsilon_finish must be in [0, 1]"),
    ],
)
def test_bad_values_name_the_key(overrides, message):
    with pytest.raises(ConfigError) as e:
        load_train_config("rdn", "matrix/four_game", overrides=overrides)
    assert message in str(e.value)


def test_unknown_algo_and_env_list_valid_names():
    with pytest.raises(
        ConfigError,
        match="valid algorithms: cac, coma, ecac, emcac, iql, mcac, qmix, qmix_ns, rdn, vdn",
    ):
        load_train_config("dqn", "matrix/four_game")
    with pytest.raises(ConfigError, match="env: unknown env 'matrix/five'; valid envs:"):
        load_train_config("rdn", "matrix/five")


def test_broken_yaml_names_file_and_line(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("algo:\n  lr: 0.1\n  gamma: [0.9\nrun: {}\n")
    with pytest.raises(ConfigError, match=r"broken YAML in .*bad.yaml, line \d"):
        read_yaml(bad)
    with pytest.raises(ConfigError, match="cannot read config file"):
        read_yaml(tmp_path / "missing.yaml")


@pytest.mark.parametrize(
    ("algo", "env", "td_lambda", "recurrent"),
    [
        ("rdn", "skirmish/3m", 0.8, True),  # envs/skirmish.rdn.yaml
        ("rdn", "smac/3m", 0.8, True),  # envs/smac.rdn.yaml
        ("rdn", "matrix/four_game", 0.0, True),  # no matrix.rdn.yaml: the seed's critic
        ("qmix", "skirmish/3m", 0.6, False),  # envs/skirmish.qmix.yaml
        ("qmix_ns", "smac/3m", 0.6, False),  # envs/smac.qmix_ns.yaml
        ("qmix", "matrix/four_game", 0.0, True),
        ("vdn", "skirmish/3m", 0.0, True),  # another algorithm's layer does not leak
        ("iql", "smac/3m", 0.0, True),
    ],
)
def test_per_algorithm_env_layer_applies_to_that_algorithm_only(algo, env, td_lambda, recurrent):
    cfg = load_train_config(algo, env, [], [])
    assert cfg.algo.td_lambda == td_lambda
    assert cfg.algo.agent.recurrent is recurrent
    assert load_train_config(algo, env, [], ["algo.td_lambda=0.3"]).algo.td_lambda == 0.3


@pytest.mark.parametrize(
    ("algo", "env", "lr"),
    [
        ("iql", "skirmish/3m", 1e-3),  # envs/skirmish.iql.yaml
        ("iql", "smac/3m", 1e-3),  # envs/smac.iql.yaml
        ("iql", "matrix/two_step", 5e-4),
        ("vdn", "skirmish/3m", 5e-4),
    ],
)
def test_iql_ships_its_measured_learning_rate_on_smac_like_maps_only(algo, env, lr):
    assert load_train_config(algo, env, [], []).algo.lr == lr


SEED_RDN = {
    "agent_targets": "taken",
    "td_lambda": 0.0,
    "lr": 5e-4,
    "agent_lr_scale": 1.0,
    "obs_window": 4,
    "critic_agent_encoder": 0,
}


def rdn_keys(cfg) -> dict:
    return {k: getattr(cfg, k) for k in SEED_RDN}


@pytest.mark.parametrize("env", ["skirmish/3m", "smac/3m"])
def test_rdn_ships_its_measured_settings_and_the_seed_recipe_is_one_key_away(env):
    shipped = load_train_config("rdn", env, [], [])
    assert shipped.recipe == "shipped"
    got = (shipped.algo.agent_targets, shipped.algo.td_lambda, shipped.algo.lr)
    assert got == ("counterfactual", 0.8, 1e-3)
    assert (shipped.algo.obs_window, shipped.algo.critic_agent_encoder) == (1, 64)
    seed = load_train_config("rdn", env, [], ["recipe=dissertation"])
    assert seed.recipe == "dissertation" and rdn_keys(seed.algo) == SEED_RDN
    # the recipe is a layer under the user's overrides, and it is recorded for resuming
    mixed = load_train_config("rdn", env, [], ["recipe=dissertation", "algo.td_lambda=0.5"])
    assert mixed.algo.td_lambda == 0.5 and mixed.algo.agent_targets == "taken"
    again = build_train_config(seed.to_yaml_dict())
    assert again == seed
    matrix = load_train_config("rdn", "matrix/four_game", [], [])
    assert rdn_keys(matrix.algo) == SEED_RDN
    assert load_train_config("rdn", "matrix/four_game", [], ["recipe=dissertation"]).algo == (
        matrix.algo
    )


def test_recipe_seed_is_an_alias_of_recipe_dissertation():
    new = load_train_config("rdn", "skirmish/3m", [], ["recipe=dissertation"])
    old = load_train_config("rdn", "skirmish/3m", [], ["recipe=seed"])
    assert old == new and old.recipe == "dissertation"
    # the config.yaml of a run made before the rename still resumes, under the new name
    saved = {**new.to_yaml_dict(), "recipe": "seed"}
    assert build_train_config(saved) == new


def test_an_unknown_recipe_names_the_valid_ones():
    with pytest.raises(
        ConfigError,
        match=r"'sead' is not a recipe of rdn; valid recipes: shipped, dissertation, "
        r"seed \(= dissertation\)",
    ):
        load_train_config("rdn", "skirmish/3m", [], ["recipe=sead"])
    with pytest.raises(ConfigError, match=r"not a recipe of vdn; valid recipes: shipped$"):
        load_train_config("vdn", "skirmish/3m", [], ["recipe=seed"])
    saved = load_train_config("rdn", "skirmish/3m").to_yaml_dict()
    with pytest.raises(ConfigError, match="'paper' is not a recipe of rdn"):
        build_train_config({**saved, "recipe": "paper"})


@pytest.mark.parametrize("algo", ["qmix", "qmix_ns"])
@pytest.mark.parametrize("env", ["skirmish/bane_vs_bane", "skirmish/bane_no_z"])
def test_recipe_gru_one_step_gives_qmix_vdns_agent_and_targets(algo, env):
    """Table 5.1's like-for-like check: with the recipe, QMIX's agent network and targets
    are VDN's, so only the mixer (and, for QMIX, the state) differs."""
    shipped = load_train_config(algo, env)
    like = load_train_config(algo, env, [], ["recipe=gru_one_step"])
    vdn = load_train_config("vdn", env)
    assert shipped.algo.agent != vdn.algo.agent or shipped.algo.td_lambda != vdn.algo.td_lambda
    assert like.algo.agent == vdn.algo.agent and like.algo.td_lambda == vdn.algo.td_lambda == 0
    for key in ("gamma", "lr", "target_update_episodes", "double_q"):
        assert getattr(like.algo, key) == getattr(vdn.algo, key), key
    assert (like.replay, like.run, like.exploration) == (vdn.replay, vdn.run, vdn.exploration)


@pytest.mark.parametrize(
    "algo, env, upe",
    [
        ("iql", "skirmish/3m", 2.0),
        ("iql", "smac/3m", 2.0),
        ("vdn", "skirmish/3m", 1.0),
        ("rdn", "smac/8m", 1.0),
    ],
)
def test_iql_ships_two_updates_per_episode_on_smac_like_maps(algo, env, upe):
    assert load_train_config(algo, env, [], []).replay.updates_per_episode == upe


@pytest.mark.parametrize(
    ("algo", "sets", "stored"),
    [
        ("rdn", [], False),
        ("vdn", [], False),
        ("iql", [], False),
        ("qmix_ns", [], False),
        ("qmix", [], True),
        ("coma", [], True),
        ("emcac", [], False),  # the seed's critic sees the joint observation
        ("emcac", ["algo.critic_input=obs_state"], True),
    ],
)
def test_the_state_is_stored_only_for_learners_that_read_it(algo, sets, stored):
    from cluster.config.plan import data_plan

    plan = data_plan(load_train_config(algo, "skirmish/3m", [], sets))
    assert plan.store_state is stored


def test_the_replay_byte_budget_is_a_config_key_in_mib():
    from buffer_service.config import DEFAULT_REPLAY_MAX_BYTES
    from cluster.commands.buffer import parse_table
    from cluster.config.plan import data_plan

    (replay,) = data_plan(load_train_config("rdn", "skirmish/3m", [], [])).tables
    assert replay.max_bytes == DEFAULT_REPLAY_MAX_BYTES
    cfg = load_train_config("rdn", "skirmish/3m", [], ["replay.max_mib=64"])
    assert data_plan(cfg).tables[0].max_bytes == 64 * 2**20
    with pytest.raises(ConfigError, match="max_mib"):
        load_train_config("rdn", "skirmish/3m", [], ["replay.max_mib=0"])
    assert parse_table("name=replay,kind=replay,capacity=10,max_bytes=4096").max_bytes == 4096

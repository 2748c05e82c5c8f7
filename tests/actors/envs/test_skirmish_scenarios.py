"""SMACv2-style randomised scenarios: sizes, per-episode unit types and start positions,
the map-file fields that describe them, and seeded reproducibility."""

from collections import Counter

import numpy as np
import pytest

from actors.envs.base import EnvError
from actors.envs.registry import env_ids, make_env, make_vec_env
from actors.envs.skirmish import SkirmishEnv, load_map_file
from actors.envs.skirmish.scripts import POLICIES, evaluate

# SMACv2's sizes (from its get_obs_size / get_state_size with the shipped configs:
# obs_own_pos, 3 type bits, shields for protoss): obs / state / n_actions; agents, enemies.
# protoss 5 v 5: 4 move + 5 x (4 + 2 + 3) + 4 x 9 + own (2 + 2 + 3) = 92;
# state 5 x (4 + 1 + 3) + 5 x (3 + 1 + 3) + 5 x 11 = 130.
SMACV2_SIZES = [
    ("protoss_5_vs_5", 92, 130, 11, 5, 5),
    ("protoss_10_vs_10", 182, 310, 16, 10, 10),
    ("protoss_10_vs_11", 191, 327, 17, 10, 11),
    ("protoss_20_vs_20", 362, 820, 26, 20, 20),
    ("terran_5_vs_5", 82, 120, 11, 5, 5),
    ("terran_10_vs_10", 162, 290, 16, 10, 10),
    ("terran_10_vs_11", 170, 306, 17, 10, 11),
    ("terran_20_vs_20", 322, 780, 26, 20, 20),
    ("zerg_5_vs_5", 82, 120, 11, 5, 5),
    ("zerg_10_vs_10", 162, 290, 16, 10, 10),
    ("zerg_10_vs_11", 170, 306, 17, 10, 11),
    ("zerg_20_vs_20", 322, 780, 26, 20, 20),
]
POOLS = {
    "protoss": {"stalker": 0.45, "zealot": 0.45, "colossus": 0.1},
    "terran": {"marine": 0.45, "marauder": 0.45, "medivac": 0.1},
    "zerg": {"zergling": 0.45, "hydralisk": 0.45, "baneling": 0.1},
}


@pytest.mark.parametrize(("name", "obs", "state", "actions", "agents", "enemies"), SMACV2_SIZES)
def test_sizes_are_smacv2s_and_fixed_across_episodes(name, obs, state, actions, agents, enemies):
    assert f"skirmish/{name}" in env_ids()
    venv = make_vec_env(f"skirmish/{name}", 3, seed=0)
    info = venv.info
    assert (info.obs_shape, info.state_shape, info.n_actions) == (obs, state, actions)
    assert (info.n_agents, info.n_enemies, info.episode_limit) == (agents, enemies, 200)
    rng = np.random.default_rng(0)
    for _ in range(3):
        venv.reset()
        for _ in range(3):
            o, s, avail = venv.get_obs(), venv.get_state(), venv.get_avail_actions()
            assert o.shape == (3, agents, obs) and s.shape == (3, state)
            assert avail.shape == (3, agents, actions) and np.isfinite(o).all()
            venv.step((avail * rng.random(avail.shape)).argmax(-1), np.ones(3, bool))


def rosters(name, episodes, seed=0):
    """(agent types, enemy types, positions [U, 2]) of `episodes` fresh episodes."""
    venv = make_vec_env(f"skirmish/{name}", episodes, seed=seed)
    venv.reset()
    b, N = venv.battle, venv.st.N
    out = []
    for m in range(episodes):
        names = b.roster(m).names
        out.append((names[:N], names[N:], np.c_[b.x[m], b.y[m]]))
    return out


@pytest.mark.parametrize("race", ["protoss", "terran", "zerg"])
def test_unit_types_follow_the_weights_and_the_enemy_mirrors_the_team(race):
    drawn = rosters(f"{race}_5_vs_5", 400)
    counts = Counter(t for allies, _, _ in drawn for t in allies)
    total = sum(counts.values())
    rare = min(POOLS[race], key=POOLS[race].get)
    for t, w in POOLS[race].items():
        # The redraw of all-rare teams (terran, zerg) lowers the rare type a little.
        assert abs(counts[t] / total - w) < 0.04, (t, counts)
    assert counts[rare] > 0
    assert all(Counter(a) == Counter(e) for a, e, _ in drawn)
    assert len({tuple(sorted(a)) for a, _, _ in drawn}) > 10  # teams vary per episode


def test_extra_enemy_and_exception_types():
    for allies, enemies, _ in rosters("terran_10_vs_11", 100):
        extra = Counter(enemies) - Counter(allies)
        assert sum(extra.values()) == 1 and "medivac" not in extra
        assert set(allies) != {"medivac"}


def test_a_team_is_never_all_exception_types(tmp_path):
    path = tmp_path / "medivacs.yaml"
    path.write_text(
        "episode_limit: 50\n"
        "team_gen: {unit_types: [marine, medivac], weights: [0.1, 0.9], "
        "exception_unit_types: [medivac]}\n"
        "n_units: 2\n"
        "start_positions: {mode: reflect}\n"
    )
    venv = make_vec_env("skirmish/custom", 200, seed=0, map_file=str(path))
    venv.reset()
    teams = [tuple(sorted(venv.battle.roster(m).names[:2])) for m in range(200)]
    assert ("medivac", "medivac") not in teams and ("marine", "medivac") in teams


def test_reflect_and_surrounded_start_positions(tmp_path):
    def map_file(mode):
        path = tmp_path / f"{mode}.yaml"
        path.write_text(
            "episode_limit: 50\n"
            "team_gen: {unit_types: [marine, marauder], weights: [0.5, 0.5]}\n"
            f"n_units: 6\nstart_positions: {{mode: {mode}}}\n"
        )
        return str(path)

    venv = make_vec_env("skirmish/custom", 50, seed=1, map_file=map_file("reflect"))
    venv.reset()
    b, N = venv.battle, 6
    for m in range(50):
        names = b.roster(m).names
        ally, enemy = np.c_[b.x[m, :N], b.y[m, :N]], np.c_[b.x[m, N:], b.y[m, N:]]
        assert (ally[:, 0] < 15.5).all() and (enemy[:, 0] > 16.5).all()
        for i in range(N):  # each agent has an enemy of its type at its mirror image
            mirror = np.hypot(enemy[:, 0] - (32 - ally[i, 0]), enemy[:, 1] - ally[i, 1])
            same = np.array([n == names[i] for n in names[N:]])
            assert mirror[same].min() < 1.5
    venv = make_vec_env("skirmish/custom", 50, seed=1, map_file=map_file("surrounded"))
    venv.reset()
    b = venv.battle
    for m in range(50):
        dx, dy = b.x[m] - 16, b.y[m] - 16
        assert (np.hypot(dx[:N], dy[:N]) < 3).all()  # agents in the middle
        assert (np.abs(np.abs(dx[N:]) - np.abs(dy[N:])) < 3).all()  # enemies on diagonals
        assert (np.hypot(dx[N:], dy[N:]) > 1.5).all()  # no nearer than 2 cells per axis


def test_surrounded_and_reflect_draws_both_modes():
    ally_x = np.array([np.mean(pos[:5, 0]) for _, _, pos in rosters("protoss_5_vs_5", 60)])
    centred = np.abs(ally_x - 16) < 2
    assert 10 < centred.sum() < 50  # p = 0.5


def test_seed_replays_episodes_and_env_k_plays_like_seed_plus_k():
    a = make_vec_env("skirmish/zerg_10_vs_10", 3, seed=5)
    b = make_vec_env("skirmish/zerg_10_vs_10", 3, seed=5)
    single = make_env("skirmish/zerg_10_vs_10", seed=7)
    assert isinstance(single, SkirmishEnv)
    rng = np.random.default_rng(0)
    for _ in range(3):
        a.reset()
        b.reset()
        single.reset()
        for _ in range(10):
            np.testing.assert_array_equal(a.get_obs(), b.get_obs())
            np.testing.assert_array_equal(a.get_state(), b.get_state())
            np.testing.assert_array_equal(a.get_obs()[2], single.get_obs())
            avail = a.get_avail_actions()
            acts = (avail * rng.random(avail.shape)).argmax(-1)
            a.step(acts, np.ones(3, bool))
            b.step(acts, np.ones(3, bool))
            single.step(acts[2])
    c = make_vec_env("skirmish/zerg_10_vs_10", 3, seed=6)
    c.reset()
    assert not np.array_equal(c.get_state(), a.get_state())


def test_own_type_and_position_features():
    venv = make_vec_env("skirmish/protoss_5_vs_5", 4, seed=2)
    venv.reset()
    obs, b = venv.get_obs(), venv.battle
    order = ["stalker", "zealot", "colossus"]
    for m in range(4):
        names = b.roster(m).names
        assert names[:5] == sorted(names[:5])  # agents ordered by type name (SMACv2)
        own = obs[m, :, -7:]  # health, shield, x / 32, y / 32, type one-hot
        np.testing.assert_allclose(own[:, 2], b.x[m, :5] / 32, atol=1e-6)
        np.testing.assert_allclose(own[:, 3], b.y[m, :5] / 32, atol=1e-6)
        assert [order[k] for k in own[:, 4:].argmax(1)] == names[:5]


@pytest.mark.parametrize("name", ["protoss_5_vs_5", "terran_5_vs_5", "zerg_5_vs_5"])
def test_random_policy_loses(name):
    venv = make_vec_env(f"skirmish/{name}", 50, seed=0)
    assert evaluate(venv, POLICIES["random"], 100, seed=0)["win_rate"] <= 0.1


BAD_FIELDS = [
    ("team_gen: {unit_types: [marine], weights: [1.0]}\n", "n_units"),
    ("team_gen: {unit_types: [tank], weights: [1.0]}\nn_units: 2\n", "team_gen.unit_types"),
    ("team_gen: {unit_types: [marine, medivac], weights: [0.5, 0.4]}\nn_units: 2\n",
     "team_gen.weights"),
    ("team_gen: {unit_types: [marine], weights: [1], exception_unit_types: [zealot]}\n"
     "n_units: 2\n", "exception_unit_types"),
    ("team_gen: {unit_types: [marine], weights: [1], count: 3}\nn_units: 2\n", "'count'"),
    ("team_gen: {unit_types: [marine], weights: [1]}\nn_units: 2\n"
     "allies: [{type: marine, count: 1, at: [1, 1]}]\n", "'allies'"),
    ("n_units: 2\nallies: [{type: marine, count: 1, at: [1, 1]}]\n"
     "enemies: [{type: marine, count: 1, at: [5, 1]}]\n", "'n_units'"),
    ("team_gen: {unit_types: [marine], weights: [1]}\nn_units: 2\n"
     "start_positions: {mode: spiral}\n", "start_positions.mode"),
    ("allies: [{type: marine, count: 1, at: [1, 1]}]\n"
     "enemies: [{type: marine, count: 1, at: [5, 1]}]\nstart_positions: {mode: reflect}\n",
     "neither 'at' nor 'positions'"),
    ("team_gen: {unit_types: [marine], weights: [1]}\nn_units: 2\nunit_ranges: yes please\n",
     "unit_ranges"),
]  # fmt: skip


@pytest.mark.parametrize(("body", "field"), BAD_FIELDS)
def test_bad_randomised_fields_are_named(tmp_path, body, field):
    path = tmp_path / "bad_random.yaml"
    path.write_text("episode_limit: 20\n" + body)
    with pytest.raises(EnvError) as e:
        load_map_file(path)
    assert "bad_random.yaml" in str(e.value) and field in str(e.value)


def test_randomised_positions_with_fixed_unit_groups(tmp_path):
    path = tmp_path / "fixed_types.yaml"
    path.write_text(
        "episode_limit: 30\n"
        "allies: [{type: marine, count: 3}, {type: medivac, count: 1}]\n"
        "enemies: [{type: zergling, count: 6}]\n"
        "start_positions: {mode: surrounded}\n"
    )
    venv = make_vec_env("skirmish/custom", 4, seed=0, map_file=str(path))
    venv.reset()
    assert venv.info.n_agents == 4 and venv.info.n_enemies == 6
    assert sorted(venv.battle.roster(0).names[:4]) == ["marine"] * 3 + ["medivac"]
    assert not np.allclose(venv.battle.x[0], venv.battle.x[1])


def test_packaged_randomised_example_file():
    from importlib import resources

    path = resources.files("actors.envs.skirmish").joinpath("data/random_example.yaml")
    venv = make_vec_env("skirmish/custom", 2, seed=0, map_file=str(path))
    # 4 + 5 x 9 + 3 x 9 + 7 = 83; state 4 x 8 + 5 x 7 + 4 x 11 = 111.
    assert (venv.info.obs_shape, venv.info.state_shape, venv.info.n_actions) == (83, 111, 11)
    venv.reset()
    assert len(venv.battle.roster(0).names) == 9

"""`StarCraft2Env`: SMAC's constructor keywords and client methods on skirmish.

Sizes are SMAC's (hand-computed from oxwhirl SMAC's get_obs_size / get_state_size); tensors
are checked against a per-agent reference written from SMAC's get_obs_agent / get_state."""

import inspect
import math

import numpy as np
import pytest

from actors.envs.base import EnvError
from actors.envs.skirmish import StarCraft2Env

# oxwhirl SMAC's StarCraft2Env.__init__ keywords and defaults, in its order.
SMAC_KEYWORDS = [
    ("map_name", "8m"), ("step_mul", 8), ("move_amount", 2), ("difficulty", "7"),
    ("game_version", None), ("seed", None), ("continuing_episode", False),
    ("obs_all_health", True), ("obs_own_health", True), ("obs_last_action", False),
    ("obs_pathing_grid", False), ("obs_terrain_height", False), ("obs_instead_of_state", False),
    ("obs_timestep_number", False), ("state_last_action", True), ("state_timestep_number", False),
    ("reward_sparse", False), ("reward_only_positive", True), ("reward_death_value", 10),
    ("reward_win", 200), ("reward_defeat", 0), ("reward_negative_scale", 0.5),
    ("reward_scale", True), ("reward_scale_rate", 20), ("replay_dir", ""), ("replay_prefix", ""),
    ("window_size_x", 1920), ("window_size_y", 1200), ("heuristic_ai", False),
    ("heuristic_rest", False), ("debug", False),
]  # fmt: skip


def test_constructor_has_every_smac_keyword_with_smacs_default():
    params = inspect.signature(StarCraft2Env).parameters
    assert [(k, p.default) for k, p in params.items()] == SMAC_KEYWORDS


# (map, keywords, obs size, state size): SMAC's numbers. 3m: 4 move + 3 enemies x 5 + 2 allies
# x 5 + own 1 = 30; state 3 x 4 + 3 x 3 + 3 x 9 last actions = 48.
SIZES = [
    ("3m", {}, 30, 48),
    ("3m", {"state_last_action": False}, 30, 21),
    ("3m", {"obs_last_action": True}, 30 + 2 * 9, 48),
    ("3m", {"obs_all_health": False}, 4 + 3 * 4 + 2 * 4 + 1, 48),
    ("3m", {"obs_all_health": False, "obs_own_health": False}, 24, 48),
    ("3m", {"obs_timestep_number": True, "state_timestep_number": True}, 31, 49),
    ("3m", {"obs_instead_of_state": True}, 30, 90),
    ("3m", {"obs_instead_of_state": True, "obs_last_action": True}, 48, 144),
    ("2s3z", {"obs_last_action": True, "state_last_action": False}, 80 + 4 * 11, 120 - 55),
    ("MMM2", {"obs_all_health": False}, 4 + 12 * 7 + 9 * 7 + 4, 322),
    ("1c3s5z", {"obs_timestep_number": True, "obs_instead_of_state": True}, 163, 9 * 163),
    ("bane_vs_bane", {"state_last_action": False}, 336, 984 - 24 * 30),
]


@pytest.mark.parametrize(("name", "kw", "obs", "state"), SIZES)
def test_sizes_equal_smacs(name, kw, obs, state):
    env = StarCraft2Env(map_name=name, seed=0, **kw)
    assert (env.get_obs_size(), env.get_state_size()) == (obs, state)
    o, s = env.reset()
    assert [x.shape for x in o] == [(obs,)] * env.n_agents and s.shape == (state,)
    assert s.dtype == np.float32 and o[0].dtype == np.float32
    info = env.get_env_info()
    assert (info["obs_shape"], info["state_shape"]) == (obs, state)


def smac_reference(env: StarCraft2Env):
    """SMAC's get_obs_agent / get_state for `env`'s keywords, one unit at a time, from the
    battle's positions and health (SMACv2's own position and unit ranges where the map says)."""
    vec, b = env.vec, env.vec.battle
    ro, spec = b.roster(0), vec.spec
    N, E, A, bits = env.n_agents, env.n_enemies, env.n_actions, env.unit_type_bits
    x, y, hp, sh, alive = b.x[0], b.y[0], b.hp[0], b.sh[0], b.alive[0]
    avail = np.array(env.get_avail_actions())
    step = env._episode_steps / env.episode_limit

    def onehot(u):
        order = spec.ally_types if u < N else spec.enemy_types
        return list(np.eye(bits)[order.index(ro.names[u])]) if bits else []

    def health(u, shields):
        return [hp[u] / ro.hp_max[u]] + ([sh[u] / ro.sh_max[u]] if shields else [])

    obs = []
    for i in range(N):
        o = []
        if alive[i]:
            s = ro.sight[i]
            o += list(avail[i, 2:6])
            for j, u in ((j, N + j) for j in range(E)):
                d = math.hypot(x[u] - x[i], y[u] - y[i])
                feats = [avail[i, 6 + j], d / s, (x[u] - x[i]) / s, (y[u] - y[i]) / s]
                feats += health(u, env.shield_bits_enemy) if env.obs_all_health else []
                n = 4 + (1 + env.shield_bits_enemy) * env.obs_all_health + bits
                o += feats + onehot(u) if d < s and alive[u] else [0.0] * n
            for j in (j for j in range(N) if j != i):
                d = math.hypot(x[j] - x[i], y[j] - y[i])
                feats = [1.0, d / s, (x[j] - x[i]) / s, (y[j] - y[i]) / s]
                feats += health(j, env.shield_bits_ally) if env.obs_all_health else []
                feats += onehot(j) + (list(env.last_action[j]) if env.obs_last_action else [])
                n = 4 + (1 + env.shield_bits_ally) * env.obs_all_health + bits
                n += A * env.obs_last_action
                o += feats if d < s and alive[j] else [0.0] * n
            o += health(i, env.shield_bits_ally) if env.obs_own_health else []
            o += [x[i] / spec.map_size[0], y[i] / spec.map_size[1]] if spec.own_pos else []
            o += onehot(i)
        else:
            o = [0.0] * (env.get_obs_size() - env.obs_timestep_number)
        obs.append(o + [step] * env.obs_timestep_number)
    if env.obs_instead_of_state:
        return np.array(obs), np.concatenate(obs)
    state, (w, h) = [], spec.map_size
    for u in range(N + E):
        feats_n = 4 + env.shield_bits_ally + bits if u < N else 3 + env.shield_bits_enemy + bits
        if not alive[u]:
            state += [0.0] * feats_n
            continue
        f = [hp[u] / ro.hp_max[u]]
        if u < N:
            cool = b.energy[0, u] if ro.names[u] == "medivac" else b.cd[0, u]
            f.append(cool / ro.smac_cd[u])
        f += [(x[u] - w / 2) / w, (y[u] - h / 2) / h]
        shields = env.shield_bits_ally if u < N else env.shield_bits_enemy
        state += f + health(u, shields)[1:] + onehot(u)
    state += list(env.last_action.ravel()) if env.state_last_action else []
    state += [step] if env.state_timestep_number else []
    return np.array(obs), np.array(state)


KEYWORD_SETS = [
    {},
    {"obs_last_action": True, "state_timestep_number": True},
    {"obs_all_health": False, "obs_timestep_number": True, "state_last_action": False},
    {"obs_all_health": False, "obs_own_health": False, "obs_last_action": True},
    {"obs_instead_of_state": True, "obs_timestep_number": True, "obs_last_action": True},
]


@pytest.mark.parametrize("name", ["3m", "2s3z", "MMM2", "protoss_5_vs_5", "terran_5_vs_5"])
@pytest.mark.parametrize("kw", KEYWORD_SETS)
def test_tensors_follow_smacs_definitions(name, kw):
    env = StarCraft2Env(map_name=name, seed=2, **kw)
    env.reset()
    rng = np.random.default_rng(0)
    for _ in range(25):
        obs, state = smac_reference(env)
        np.testing.assert_allclose(np.array(env.get_obs()), obs, atol=1e-5)
        np.testing.assert_allclose(env.get_state(), state, atol=1e-5)
        avail = np.array(env.get_avail_actions())
        _, term, _ = env.step((avail * rng.random(avail.shape)).argmax(-1))
        if term:
            env.reset()


def far_apart_map(tmp_path, limit=4):
    path = tmp_path / "far_apart.yaml"
    path.write_text(
        f"episode_limit: {limit}\n"
        "allies: [{type: marine, count: 2, at: [2, 16]}]\n"
        "enemies: [{type: marine, count: 2, at: [30, 16]}]\n"
    )
    return str(path)


def duel_map(tmp_path, allies=1, enemies=1):
    """Marines in range of the enemy's marines; all fire on the first step."""
    path = tmp_path / f"duel_{allies}_{enemies}.yaml"
    ally_pos = [[10, 10 + k] for k in range(allies)]
    enemy_pos = [[14, 10 + k] for k in range(enemies)]
    path.write_text(
        "episode_limit: 50\n"
        f"allies: [{{type: marine, count: {allies}, positions: {ally_pos}}}]\n"
        f"enemies: [{{type: marine, count: {enemies}, positions: {enemy_pos}}}]\n"
    )
    return str(path)


def play_attacking(env) -> tuple[list[float], dict]:
    """One episode in which every agent attacks the first enemy it can, else stops."""
    env.reset()
    rewards, term, info = [], False, {}
    while not term:
        acts = []
        for avail in env.get_avail_actions():
            attacks = [a for a in range(6, len(avail)) if avail[a]]
            acts.append(attacks[0] if attacks else (1 if avail[1] else 0))
        r, term, info = env.step(acts)
        rewards.append(r)
    return rewards, info


@pytest.mark.parametrize("continuing", [False, True])
def test_continuing_episode_sets_episode_limit_only_when_asked(tmp_path, continuing):
    env = StarCraft2Env(map_name=far_apart_map(tmp_path), continuing_episode=continuing)
    env.reset()
    steps = [env.step([1, 1]) for _ in range(4)]
    assert [t for _, t, _ in steps] == [False, False, False, True]
    assert all("episode_limit" not in i for _, _, i in steps[:3])
    assert steps[-1][2].get("episode_limit", False) is continuing
    assert steps[-1][2]["battle_won"] is False
    assert env.get_stats()["timeouts"] == 1 and env.get_stats()["battles_draw"] == 1


def test_negative_rewards_use_reward_negative_scale(tmp_path):
    """Both marines deal 6: reward 6 - scale x 6 (unscaled), as SMAC's reward_battle."""
    for neg in (0.5, 0.25):
        env = StarCraft2Env(
            map_name=duel_map(tmp_path), reward_only_positive=False,
            reward_negative_scale=neg, reward_scale=False, seed=0,
        )  # fmt: skip
        env.reset()
        env.vec.battle.f[0, :2] = [[10, 14], [10, 10]]  # exact positions, no start jitter
        r, _, _ = env.step([6])
        assert r == pytest.approx(6 - neg * 6)


@pytest.mark.parametrize(("allies", "enemies", "end"), [(2, 1, 1.0), (1, 2, -1.0), (1, 1, 0.0)])
def test_sparse_reward_is_plus_minus_one_at_the_end(tmp_path, allies, enemies, end):
    """+1 for a win, -1 for a defeat, 0 when both sides die in the same step (SMAC's draw)."""
    path = duel_map(tmp_path, allies, enemies)
    env = StarCraft2Env(map_name=path, reward_sparse=True, reward_scale=False, seed=0)
    rewards, info = play_attacking(env)
    assert rewards == [0.0] * (len(rewards) - 1) + [end]
    assert info["battle_won"] is (end > 0)
    # SMAC also divides the sparse reward by max_reward / reward_scale_rate when scaling:
    # max_reward = enemies x (45 + 10) + 200.
    env = StarCraft2Env(map_name=path, reward_sparse=True, seed=0)
    rewards, _ = play_attacking(env)
    assert rewards[-1] == pytest.approx(end * 20 / (enemies * 55 + 200))


def test_reward_keywords_scale_a_won_episode():
    """A won 3m episode returns reward_scale_rate in total, whatever the other values."""
    from actors.envs.skirmish.scripts import focus_fire_policy

    for kw in ({}, {"reward_scale_rate": 10, "reward_death_value": 5, "reward_win": 100}):
        env = StarCraft2Env(map_name="3m", seed=0, **kw)
        rng, won = np.random.default_rng(0), False
        while not won:
            env.reset()
            total, term = 0.0, False
            while not term:
                r, term, info = env.step(focus_fire_policy(env.vec, rng)[0])
                total += r
            won = info["battle_won"]
        assert total == pytest.approx(kw.get("reward_scale_rate", 20), rel=1e-4)


@pytest.mark.parametrize(
    ("kw", "word"),
    [
        ({"obs_pathing_grid": True}, "obs_pathing_grid"),
        ({"obs_terrain_height": True}, "obs_terrain_height"),
        ({"difficulty": "11"}, "difficulty"),
        ({"step_mul": 0}, "step_mul"),
        ({"reward_negative_scale": -1}, "reward_negative_scale"),
        ({"reward_win": "lots"}, "reward_win"),
        ({"map_name": "no_such_map"}, "no_such_map"),
    ],
)
def test_values_skirmish_cannot_honour_raise_naming_the_keyword(kw, word):
    with pytest.raises(EnvError, match=word):
        StarCraft2Env(**{"map_name": "3m", **kw})


def test_heuristic_ai_attacks_the_nearest_enemy_and_writes_its_actions_back():
    env = StarCraft2Env(map_name="3m", heuristic_ai=True, seed=0)
    env.reset()
    b = env.vec.battle
    _, _, dist = b.pairwise()
    acts = [1, 1, 1]
    env.step(acts)
    assert acts == (6 + dist[0, :3, 3:].argmin(1)).tolist()  # attack orders, out of range too
    assert (b.order[0, :3] == 2).all()  # ATTACK: they chase their targets
    np.testing.assert_array_equal(env.last_action, np.eye(9)[[1, 1, 1]])  # SMAC: the passed
    targets = list(env.heuristic_targets)
    for _ in range(3):
        env.step([1, 1, 1])
        kept = [t for t in targets if b.alive[0, 3 + t]]
        assert all(env.heuristic_targets[i] == t for i, t in enumerate(targets) if t in kept)
    rest = StarCraft2Env(map_name="3m", heuristic_ai=True, heuristic_rest=True, seed=0)
    rest.reset()
    acts = [1, 1, 1]
    rest.step(acts)
    assert acts == [4, 4, 4]  # 10 cells apart, out of range: move east towards the target


def test_starcraft_only_keywords_are_accepted(tmp_path):
    kw = dict(game_version="4.10", difficulty="A", window_size_x=640, window_size_y=480,
              heuristic_rest=True, debug=True, replay_dir=str(tmp_path))  # fmt: skip
    # (heuristic_rest without heuristic_ai changes nothing, as in SMAC)
    env = StarCraft2Env(map_name="3m", seed=0, **kw)
    ref = StarCraft2Env(map_name="3m", seed=0)
    np.testing.assert_array_equal(env.reset()[1], ref.reset()[1])
    assert env.window_size == (640, 480) and env.difficulty == "A"


def test_step_mul_and_move_amount_are_honoured():
    """A marine (3.15 cells/s) ordered east: 8 game loops at 22.4 per second move it 1.125,
    4 loops half that; a move order ends move_amount away (SMAC orders a point there)."""
    envs = {
        "base": StarCraft2Env(map_name="3m", seed=0),
        "step_mul": StarCraft2Env(map_name="3m", seed=0, step_mul=4),
        "short": StarCraft2Env(map_name="3m", seed=0, move_amount=0.5),
    }
    moved = {}
    for key, env in envs.items():
        env.reset()
        x0 = env.vec.battle.x[0, 0]
        env.step([4, 1, 1])
        moved[key] = env.vec.battle.x[0, 0] - x0
    speed = 3.15 / 22.4
    assert moved["base"] == pytest.approx(8 * speed)
    assert moved["step_mul"] == pytest.approx(4 * speed)
    assert moved["short"] == pytest.approx(0.5)


def test_client_methods():
    env = StarCraft2Env(map_name="2s3z", seed=1)
    obs, _ = env.reset()
    assert isinstance(obs, list) and len(obs) == 5
    for i in range(5):
        np.testing.assert_array_equal(env.get_obs_agent(i), obs[i])
        avail = env.get_avail_agent_actions(i)
        assert isinstance(avail, list) and avail == env.get_avail_actions()[i]
        assert all(type(v) is int for v in avail) and avail[:2] == [0, 1]
    assert env.get_total_actions() == 11 == env.n_actions
    info = env.get_env_info()
    assert set(info) == {"state_shape", "obs_shape", "n_actions", "n_agents", "episode_limit",
                         "agent_features", "enemy_features"}  # fmt: skip
    assert info["agent_features"][:4] == ["health", "energy/cooldown", "rel_x", "rel_y"]
    assert len(info["agent_features"]) == 4 + 1 + 2 and len(info["enemy_features"]) == 3 + 1 + 2
    vis = env.get_visibility_matrix()
    assert vis.shape == (5, 10) and not vis[np.arange(5), np.arange(5)].any()
    frame = env.render(mode="rgb_array")
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.dtype == np.uint8
    with pytest.raises(EnvError, match="render mode"):
        env.render(mode="video")
    stats = env.get_stats()
    assert stats == {"battles_won": 0, "battles_game": 0, "battles_draw": 0, "win_rate": 0.0,
                     "timeouts": 0, "restarts": 0}  # fmt: skip
    env.close()


def test_seed_with_and_without_argument_replays_episodes():
    env = StarCraft2Env(map_name="protoss_5_vs_5", seed=7)
    assert env.seed() == 7
    first = env.reset()[1].copy()
    second = env.reset()[1].copy()
    assert not np.array_equal(first, second)
    assert env.seed(7) == 7
    np.testing.assert_array_equal(env.reset()[1], first)
    assert env.seed(8) == 8 and env.seed() == 8
    np.testing.assert_array_equal(env.reset()[1], StarCraft2Env(map_name="protoss_5_vs_5",
                                                                seed=8).reset()[1])  # fmt: skip


def test_save_replay_writes_a_gif_of_the_episodes(tmp_path):
    from PIL import Image

    env = StarCraft2Env(map_name=far_apart_map(tmp_path, limit=3), replay_dir=str(tmp_path),
                        replay_prefix="run")  # fmt: skip
    assert env.save_replay() is None  # nothing played yet
    for _ in range(2):
        env.reset()
        term = False
        while not term:
            _, term, _ = env.step([1, 1])
    path = env.save_replay()
    assert path is not None and path.startswith(str(tmp_path / "run_")) and path.endswith(".gif")
    with Image.open(path) as gif:
        assert gif.n_frames == 2 * (3 + 1)  # two episodes of 3 steps, plus their start
    assert env.save_replay() is None  # each call writes the episodes since the last one


def test_bad_actions_raise_env_errors():
    env = StarCraft2Env(map_name="3m", seed=0)
    with pytest.raises(EnvError, match="finished episode"):
        env.step([1, 1, 1])  # before reset
    env.reset()
    with pytest.raises(EnvError, match="expected 3 actions"):
        env.step([1, 1])
    with pytest.raises(EnvError, match="agent 0 cannot take action 0"):
        env.step([0, 1, 1])
    with pytest.raises(EnvError, match="agent 1 cannot take action 42"):
        env.step([1, 42, 1])
    np.testing.assert_array_equal(env.last_action, 0)  # nothing was taken

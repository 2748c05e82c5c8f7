"""SMAC semantics of the skirmish tensors, checked against a plain per-agent loop written
from SMAC's definitions (not from our vectorised code), and the env's error messages."""

import math

import numpy as np
import pytest

from actors.envs.base import EnvError
from actors.envs.registry import make_env
from actors.envs.skirmish import SkirmishEnv, SkirmishVecEnv, builtin_map, load_map_file
from actors.envs.skirmish.scripts import focus_fire_policy


def reference_obs_state_avail(env: SkirmishEnv):
    """SMAC's get_obs_agent / get_state / get_avail_agent_actions, one unit at a time."""
    b, lay, st = env.battle, env.vec.lay, env.vec.st
    onehots = b.roster(0).onehot
    N, E, bits = st.N, st.E, lay.bits
    x, y, hp, sh, alive = b.x[0], b.y[0], b.hp[0], b.sh[0], b.alive[0]
    sight, shoot = 9.0, 6.0

    def onehot(u):
        return list(onehots[u]) if bits else []

    def health_feats(u, shields):
        f = [hp[u] / st.hp_max[u]]
        if shields:
            f.append(sh[u] / st.sh_max[u])
        return f

    avail = np.zeros((N, 6 + E))
    for i in range(N):
        if not alive[i]:
            avail[i, 0] = 1
            continue
        avail[i, 1] = 1
        avail[i, 2] = int(y[i] + 1) < st.map_h
        avail[i, 3] = int(y[i] - 1) >= 0
        avail[i, 4] = int(x[i] + 1) < st.map_w
        avail[i, 5] = int(x[i] - 1) >= 0
        healer = st.types[i].kind == "healer"
        targets = (
            [(j, j) for j in range(min(N, E)) if st.types[j].kind != "healer"]
            if healer
            else [(j, N + j) for j in range(E)]
        )
        for j, u in targets:
            if alive[u] and math.hypot(x[u] - x[i], y[u] - y[i]) <= shoot:
                avail[i, 6 + j] = 1
    obs = []
    for i in range(N):
        o = []
        if alive[i]:
            o += list(avail[i, 2:6])
            for j in range(E):
                u = N + j
                d = math.hypot(x[u] - x[i], y[u] - y[i])
                if d < sight and alive[u]:
                    o += [avail[i, 6 + j], d / sight, (x[u] - x[i]) / sight, (y[u] - y[i]) / sight]
                    o += health_feats(u, lay.sh_enemy) + onehot(u)
                else:
                    o += [0.0] * lay.nf_en
            for j in range(N):
                if j == i:
                    continue
                d = math.hypot(x[j] - x[i], y[j] - y[i])
                if d < sight and alive[j]:
                    o += [1.0, d / sight, (x[j] - x[i]) / sight, (y[j] - y[i]) / sight]
                    o += health_feats(j, lay.sh_ally) + onehot(j)
                else:
                    o += [0.0] * lay.nf_al
            o += health_feats(i, lay.sh_ally) + onehot(i)
        else:
            o = [0.0] * lay.obs_dim
        obs.append(o)
    state = []
    cx, cy = st.map_w / 2, st.map_h / 2
    for i in range(N):
        if not alive[i]:
            state += [0.0] * lay.nf_al_state
            continue
        cool = b.energy[0, i] if st.types[i].kind == "healer" else b.cd[0, i]
        state += [hp[i] / st.hp_max[i], cool / st.smac_cd[i], (x[i] - cx) / st.map_w]
        state += [(y[i] - cy) / st.map_h, *health_feats(i, lay.sh_ally)[1:], *onehot(i)]
    for u in range(N, N + E):
        if not alive[u]:
            state += [0.0] * lay.nf_en_state
            continue
        state += [hp[u] / st.hp_max[u], (x[u] - cx) / st.map_w, (y[u] - cy) / st.map_h]
        state += health_feats(u, lay.sh_enemy)[1:] + onehot(u)
    state += list(env.vec.last_action[0].ravel())
    return np.array(obs), np.array(state), avail


@pytest.mark.parametrize("name", ["3m", "2s3z", "1c3s5z", "MMM2", "bane_no_z"])
def test_tensors_match_smac_reference(name):
    env = make_env(f"skirmish/{name}", seed=3)
    env.reset()
    rng = np.random.default_rng(0)
    for t in range(30):
        obs, state, avail = reference_obs_state_avail(env)
        np.testing.assert_array_equal(env.get_avail_actions(), avail)
        np.testing.assert_allclose(env.get_obs(), obs, atol=1e-5)
        np.testing.assert_allclose(env.get_state(), state, atol=1e-5)
        dead = ~env.battle.alive[0, : env.n_agents]
        assert (env.get_obs()[dead] == 0).all()
        a = (
            (avail * rng.random(avail.shape)).argmax(-1)
            if t % 2
            else focus_fire_policy(env.vec, rng)[0]
        )
        _, term, _ = env.step(a)
        if term:
            env.reset()


def test_won_episode_returns_exactly_twenty():
    """3m: max_reward = 3 x 45 health + 3 x 10 kills + 200 win = 365, scaled to 20."""
    env = make_env("skirmish/3m", seed=0)
    assert env.vec.max_reward == pytest.approx(365.0)
    rng = np.random.default_rng(0)
    won_returns = []
    for _ in range(10):
        env.reset()
        ret, term, info = 0.0, False, {}
        while not term:
            r, term, info = env.step(focus_fire_policy(env.vec, rng)[0])
            ret += r
        if info["battle_won"]:
            won_returns.append(ret)
            assert info["episode_limit"] is False
    assert won_returns and np.allclose(won_returns, 20.0, atol=1e-4)
    stats = env.get_stats()
    assert stats["battles_game"] == 10 and stats["battles_won"] == len(won_returns)


def test_timeout_sets_episode_limit_and_is_no_win(tmp_path):
    path = tmp_path / "far.yaml"
    path.write_text(
        "episode_limit: 3\nallies: [{type: marine, count: 1, at: [2, 16]}]\n"
        "enemies: [{type: marine, count: 1, at: [30, 16]}]\n"
    )
    env = make_env("skirmish/custom", seed=0, map_file=str(path))
    env.reset()
    infos = [env.step([1]) for _ in range(3)]
    assert [t for _, t, _ in infos] == [False, False, True]
    assert infos[-1][2]["episode_limit"] is True and infos[-1][2]["battle_won"] is False
    with pytest.raises(EnvError, match="finished episode"):
        env.step([1])
    assert env.get_stats()["timeouts"] == 1


def test_unavailable_action_names_agent_and_action():
    env = make_env("skirmish/3m", seed=0)
    env.reset()
    with pytest.raises(EnvError, match=r"agent 1 cannot take action 0"):
        env.step([1, 0, 1])  # no-op while alive
    with pytest.raises(EnvError, match=r"agent 2 cannot take action 6"):
        env.step([1, 1, 6])  # enemy 0 is out of shoot range at the start


def test_unknown_map_lists_valid_maps():
    with pytest.raises(EnvError, match=r"unknown skirmish map 'nope'.*3m.*bane_vs_bane"):
        builtin_map("nope")


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("episode_limit: 0\nallies: []\nenemies: []\n", "'episode_limit'"),
        ("episode_limit: 5\nallies: [{type: tank, count: 1, at: [1, 1]}]\n", "'allies[0]'.type"),
        (
            "episode_limit: 5\nallies: [{type: marine, count: -1, at: [1, 1]}]\n",
            "'allies[0]'.count",
        ),
        ("episode_limit: 5\nspeed: 3\n", "'speed'"),
    ],
)
def test_bad_custom_map_names_field_and_file(tmp_path, text, field):
    path = tmp_path / "bad_map.yaml"
    path.write_text(text)
    with pytest.raises(EnvError) as e:
        load_map_file(path)
    assert "bad_map.yaml" in str(e.value) and field in str(e.value)


def test_custom_map_file_builds_variant(tmp_path):
    path = tmp_path / "bane_12z.yaml"
    path.write_text(
        "episode_limit: 150\n"
        "type_order: {allies: [baneling, zergling], enemies: [baneling, zergling]}\n"
        "allies: [{type: zergling, count: 12, at: [11, 16]},\n"
        "         {type: baneling, count: 4, at: [8, 16]}]\n"
        "enemies: [{type: zergling, count: 20, at: [21, 16]},\n"
        "          {type: baneling, count: 4, at: [24, 16]}]\n"
    )
    venv = SkirmishVecEnv(load_map_file(path), 2, seed=0)
    assert (venv.info.n_agents, venv.info.n_enemies, venv.info.episode_limit) == (16, 24, 150)
    # 4 + 24 x 7 + 15 x 7 + 3, as SMAC computes it for a bane map with 16 agents.
    assert venv.info.obs_shape == 4 + 24 * 7 + 15 * 7 + 3


def test_blob_formation_and_attack_point(tmp_path):
    # SC2-style spawn: every unit of a side on the free spot nearest its point, no overlaps;
    # the enemy's attack-move goal is the given point (shifted with the agents' formation).
    path = tmp_path / "blob.yaml"
    path.write_text(
        "episode_limit: 20\nformation: blob\nattack_point: [9, 16]\n"
        "allies: [{type: stalker, count: 2, at: [9, 16]}, {type: zealot, count: 3, at: [9, 16]}]\n"
        "enemies: [{type: zealot, count: 3, at: [23, 16]}]\n"
    )
    spec = load_map_file(path)
    venv = SkirmishVecEnv(spec, 1, seed=0)
    st = venv.st
    pos, r = st.start_pos[: st.N], st.radius[: st.N]
    gaps = np.hypot(*(pos[:, None] - pos[None]).transpose(2, 0, 1)) - r[:, None] - r[None]
    assert (gaps[~np.eye(st.N, dtype=bool)] >= 0).all()
    assert np.abs(pos - [9, 16]).max() < 2.5
    np.testing.assert_allclose(st.goal, [9, 16])
    path.write_text(path.read_text().replace("blob", "square"))
    with pytest.raises(EnvError, match=r"blob.yaml.*'formation'"):
        load_map_file(path)


def test_bench_time_env_reports_best_and_median_blocks():
    from cluster.bench.env import time_env

    fig = time_env("skirmish/3m", 4, 5, seed=0, repeats=2)
    assert fig["repeats"] == 2 and len(fig["block_seconds"]) == 2
    assert fig["env_steps_per_s"] >= fig["env_steps_per_s_median"] > 0
    assert fig["agent_steps_per_s"] == pytest.approx(3 * fig["env_steps_per_s"])

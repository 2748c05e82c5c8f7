"""The one training loop in one process (`cluster.loop`): what local mode now shares with
cluster mode (validation, the limiter on inserts, max_policy_lag, replay kept on resume,
seeds), the typed messages and the acting network described by the learner."""

import dataclasses

import numpy as np
import pytest
import torch

from actors.envs.registry import make_vec_env
from actors.policy import ExplorationConfig
from actors.rollout import RolloutWorker
from buffer_service.config import RateLimiterConfig, TableConfig
from buffer_service.episode import EpisodeError
from buffer_service.local import LocalBuffer
from buffer_service.tables import Table
from cluster.commands.buffer import parse_table
from cluster.config.plan import data_plan
from cluster.config.schema import ConfigError
from cluster.config.train import load_train_config
from cluster.launch.buffer_proc import table_arg
from cluster.launch.local import LocalTrainer
from cluster.messages import ActorConfig, actor_seed
from cluster.process import configure
from learner.registry import ALGOS

TWO_STEP = ["run.test_interval=50", "replay.batch_size=4", "replay.capacity=100000"]


def _cfg(algo="vdn", env="matrix/two_step", *sets):
    return load_train_config(algo, env, [], [*TWO_STEP, *sets])


def _trainer(*sets: str, **kwargs) -> LocalTrainer:
    """A local VDN trainer on matrix/two_step, its process configured as an entry point does."""
    cfg = _cfg("vdn", "matrix/two_step", *sets)
    configure(cfg.run)
    return LocalTrainer(cfg, **kwargs)


def test_local_inserts_are_validated_against_the_schema():
    trainer = _trainer("run.t_max=4")
    trainer.train()
    good = trainer.data.buffers[0].sample_episodes("replay", 1)[0].unpack()  # (no state: vdn)
    bad = dataclasses.replace(good, actions=good.actions + 100, episode_seq=10**9)
    with pytest.raises(EpisodeError, match="actions"):
        trainer.data.insert([bad], 1)
    # all or nothing, as in the service: the good episode of the same insert is not stored
    fresh = dataclasses.replace(good, episode_seq=10**9 + 1)
    with pytest.raises(EpisodeError):
        trainer.data.buffers[0].insert([fresh, bad])
    assert fresh.key not in trainer.data.buffers[0].state.episodes


def test_a_held_back_local_insert_waits_for_the_learner_to_catch_up():
    """Rounds inserted without their updates put the learner behind the limiter's slack;
    the loop's `catch_up` then takes exactly the updates the limiter needs, as a Ray actor's
    insert would wait for them."""
    trainer = _trainer("run.t_max=1000")
    data = trainer.data
    for _ in range(20):  # 20 episodes, no updates
        trainer.acting.act(0, 0)
    assert not data.buffers[0].can_insert()
    taken = list(data.catch_up())
    assert taken and data.buffers[0].can_insert()
    table = data.buffers[0].state.tables["replay"]
    limiter = table.limiter
    # just inside the window again: one batch fewer would still hold the insert back
    limiter.samples -= 4
    assert not limiter.can_insert(1)


def test_local_deadlock_of_the_limiter_is_an_error_not_a_hang():
    from cluster.loop import RateLimitDeadlockError

    trainer = _trainer("run.t_max=1000")
    for _ in range(20):
        trainer.acting.act(0, 0)
    trainer.data.buffers[0].state.tables["replay"].order.clear()
    with pytest.raises(RateLimitDeadlockError, match="rate limiter"):
        list(trainer.data.catch_up())


def test_extended_pg_tables_pass_their_joint_warm_up():
    """E-CAC steps only once the replay table holds a batch; the cycling table's limiter
    must let that many inserts in (before: a 32-episode replay batch with an 8-episode cycling
    table held inserts back at 16 episodes, forever)."""
    cfg = load_train_config("emcac", "matrix/four_game", [], ["cycling.capacity=8"])
    plan = data_plan(cfg, actors=1)
    tables = {t.name: Table(t) for t in plan.tables}
    for seq in range(plan.extra_batch_size):
        assert all(t.limiter.can_insert(1) for t in tables.values()), seq
        for t in tables.values():
            t.insert((0, seq))
    assert tables["cycling"].ready(plan.batch_size)
    assert tables["replay"].ready(plan.extra_batch_size)


def test_max_policy_lag_drops_stale_episodes_in_local_mode():
    lagged = _trainer("run.t_max=300", "run.max_policy_lag=2")
    lagged.train()
    free = _trainer("run.t_max=300")
    free.train()
    assert lagged.stats.dropped_stale > 0 and free.stats.dropped_stale == 0
    assert max(lagged.stats.lag_counts) > 2  # stale episodes were sampled, then dropped
    assert lagged.core.learner.updates > 0


def test_modes_refuse_what_they_cannot_do_naming_the_key(tmp_path):
    with pytest.raises(ConfigError, match=r"run\.max_policy_lag"):
        _trainer("run.max_policy_lag=3", n_ensemble=2)
    pytest.importorskip("ray")
    from cluster.launch.cluster import ClusterTrainer

    with pytest.raises(ConfigError, match="n_ensemble=2"):
        ClusterTrainer(_cfg(), tmp_path, n_ensemble=2)


def _learner_state(trainer):
    return {k: v.clone() for k, v in trainer.core.learner.state_dict()["agent"].items()}


def test_local_resume_keeps_the_replay_and_continues_exactly(tmp_path):
    """Train 300 steps in one go, or 150, checkpoint, resume in a new trainer and train to
    300: the same weights, because the replay (and its sampling RNG) came back too."""
    straight = _trainer("run.t_max=300")
    straight.train()
    first = _trainer("run.t_max=150")
    first.train()
    first.save(tmp_path / "ckpt")
    assert (tmp_path / "ckpt" / "buffer" / "member-0").is_dir()
    resumed = _trainer("run.t_max=300")
    resumed.restore(tmp_path / "ckpt")
    held = resumed.data.buffers[0].stats()["tables"]["replay"]
    assert held == first.data.buffers[0].stats()["tables"]["replay"] and held["size"] > 0
    resumed.train()
    assert resumed.core.learner.updates == straight.core.learner.updates
    a, b = _learner_state(straight), _learner_state(resumed)
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_a_checkpoint_without_the_replay_holds_the_networks_and_resumes_with_an_empty_one(
    tmp_path,
):
    """`save(path, replay=False)` (what `credit repro --checkpoints` writes): no buffer
    tables, the same learner state, and a resumed run starts from an empty replay."""
    first = _trainer("run.t_max=150")
    first.train()
    first.save(tmp_path / "full")
    first.save(tmp_path / "small", replay=False)
    assert (tmp_path / "full" / "buffer").is_dir()
    assert not (tmp_path / "small" / "buffer").exists()
    full = torch.load(tmp_path / "full" / "learner.pt", weights_only=False)
    small = torch.load(tmp_path / "small" / "learner.pt", weights_only=False)
    assert all(torch.equal(full["agent"][k], small["agent"][k]) for k in full["agent"])
    resumed = _trainer("run.t_max=300")
    resumed.restore(tmp_path / "small")
    assert resumed.core.t_env == first.core.t_env
    assert resumed.data.buffers[0].stats()["tables"]["replay"]["size"] == 0
    a, b = _learner_state(first), _learner_state(resumed)
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_actor_seeds_come_from_the_run_seed_and_actor_id_only():
    assert actor_seed(7, 0) == 7  # the local worker is actor 0
    seeds = {actor_seed(7, i) for i in range(1, 50)}
    assert len(seeds) == 49 and 7 not in seeds
    assert actor_seed(7, 3) == actor_seed(7, 3) != actor_seed(8, 3)


def test_buffer_service_tables_keep_replacement_on_the_command_line():
    t = TableConfig(
        name="replay",
        kind="replay",
        capacity=50,
        replacement=False,
        rate_limiter=RateLimiterConfig(min_size_to_sample=4, samples_per_insert=4.0),
    )
    back = parse_table(table_arg(t))
    assert back.replacement is False
    assert back == dataclasses.replace(t, rate_limiter=back.rate_limiter)


def test_actor_config_holds_only_the_actor_section(tmp_path):
    pytest.importorskip("ray")
    from cluster.launch.cluster import ClusterTrainer

    trainer = ClusterTrainer(_cfg("qmix", "matrix/two_step", "run.seed=5"), tmp_path)
    ac = trainer.acting.actor_config(2)
    assert isinstance(ac, ActorConfig)
    assert ac.seed == actor_seed(5, 2) and ac.env_id == "matrix/two_step"
    assert ac.acting == trainer.core.learner.acting
    assert {f.name for f in dataclasses.fields(ac)} == {
        "actor_id",
        "env_id",
        "env_args",
        "num_envs",
        "seed",
        "exploration",
        "acting",
        "metrics",
        "bind_host",
        "send_state",
    }
    assert ac.send_state  # qmix's mixer reads the state


@pytest.mark.parametrize("name", sorted(ALGOS))
def test_acting_network_is_built_from_the_learners_description(name):
    """An actor's network built from `learner.acting`, loaded with the learner's weights,
    acts exactly as the learner's own agent network."""
    cfg = load_train_config(name, "matrix/two_step", [], [])
    venv = make_vec_env(cfg.env.id, 2, seed=0, **cfg.env.args)
    torch.manual_seed(0)
    learner = ALGOS[name].build(cfg.algo, venv.info.schema(), 1, "cpu")
    spec = learner.acting
    assert spec.layout.width == learner.agent.input_dim
    assert spec.policy_kind == learner.policy_kind
    own = RolloutWorker(venv, learner.agent, learner.policy_kind, ExplorationConfig(), seed=1)
    venv2 = make_vec_env(cfg.env.id, 2, seed=0, **cfg.env.args)
    remote = RolloutWorker.from_spec(venv2, spec, ExplorationConfig(), seed=1)
    remote.set_weights(learner.get_weights())
    a, b = own.run_round(t_env=0), remote.run_round(t_env=0)
    for x, y in zip(a.episodes, b.episodes, strict=True):
        np.testing.assert_array_equal(x.actions, y.actions)


@pytest.mark.parametrize("greedy", [True, False])
def test_a_round_without_records_plays_the_same_episodes(greedy):
    """`run_round(record=False)` (what the evaluation uses) keeps no episodes but plays what a
    recording round plays: the same returns, wins and steps, greedy and exploring; the
    worker's env-step count moves the same way."""
    cfg = load_train_config("vdn", "skirmish/3m", [], [])
    schema = make_vec_env(cfg.env.id, 1).info.schema()
    torch.manual_seed(0)
    agent = cfg.algo.agent.build(2, schema)
    results, counts = [], []
    for record in (True, False):
        venv = make_vec_env(cfg.env.id, 8, seed=3)
        worker = RolloutWorker(venv, agent, "q", ExplorationConfig(0.5, 0.5, 1), 2, seed=1)
        results.append([worker.run_round(greedy=greedy, record=record) for _ in range(2)])
        counts.append(worker.t_env)
    for kept, bare in zip(*results, strict=True):
        assert len(kept.episodes) == 8 and bare.episodes == []
        np.testing.assert_array_equal(kept.returns, bare.returns)
        np.testing.assert_array_equal(kept.won, bare.won)
        assert kept.env_steps == bare.env_steps
        assert kept.env_steps == sum(ep.length for ep in kept.episodes)
    assert counts[0] == counts[1] > 0


def test_a_worker_refuses_a_network_of_another_input_width():
    cfg = load_train_config("vdn", "matrix/two_step", [], [])
    venv = make_vec_env(cfg.env.id, 1, seed=0, **cfg.env.args)
    schema = venv.info.schema()
    spec = cfg.algo.agent.acting_spec(dataclasses.replace(schema, obs_dim=schema.obs_dim + 3), "q")
    with pytest.raises(ValueError, match="inputs per agent"):
        RolloutWorker.from_spec(venv, spec, ExplorationConfig())


def test_local_buffer_writes_and_reads_the_service_snapshot_format(tmp_path):
    from buffer_service.state import BufferState
    from buffer_service.storage import Storage

    trainer = _trainer("run.t_max=40")
    trainer.train()
    buf = trainer.data.buffers[0]
    buf.write(tmp_path / "snap")
    # what a buffer service (or `credit buffer verify`) restores from that folder
    state = BufferState(buf.state.cfg)
    Storage(str(tmp_path / "snap"), read_only=True).restore(state)
    assert list(state.episodes) == list(buf.state.episodes)
    copy = LocalBuffer(buf.tables, schema=buf.state.schema)
    copy.read(tmp_path / "snap")
    assert copy.stats() == buf.stats()


def test_periodic_checkpoints_hold_the_tables(tmp_path):
    trainer = _trainer("run.t_max=100", "run.save_interval=40", checkpoint_dir=tmp_path / "ckpt")
    trainer.train()  # no save at the end: only the periodic ones
    saved = torch.load(tmp_path / "ckpt" / "trainer.pt", weights_only=False)
    assert 40 <= saved["t_env"] < 100
    copy = LocalBuffer(trainer.data.plan.tables)
    copy.read(tmp_path / "ckpt" / "buffer" / "member-0")
    assert copy.stats()["tables"]["replay"]["inserts"] == saved["episodes"]


def test_an_older_runs_cluster_max_policy_lag_is_read_as_run_max_policy_lag():
    old = load_train_config("vdn", "matrix/two_step", [], ["cluster.max_policy_lag=4"])
    assert old.run.max_policy_lag == 4
    with pytest.raises(ConfigError, match=r"run\.max_policy_lag"):
        load_train_config(
            "vdn", "matrix/two_step", [], ["cluster.max_policy_lag=4", "run.max_policy_lag=2"]
        )

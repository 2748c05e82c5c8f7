"""Device plumbing: the learner may live on another device while this process's rollout and
evaluation workers act on CPU copies of its weights (`run.acting_weights`)."""

from __future__ import annotations

import pytest
import torch

from cluster.config.schema import ConfigError
from cluster.config.train import load_train_config
from cluster.launch.local import LocalTrainer
from cluster.process import configure

# QMIX on skirmish/3m, small enough for the fast tier: recurrent agents, the mixer, the replay
# and the greedy evaluation all run; a batch of 4 from the first 8 episodes.
SMALL = [
    "run.t_max=900",
    "run.num_envs=2",
    "run.test_interval=300",
    "run.test_episodes=2",
    "replay.batch_size=4",
    "replay.capacity=64",
]


def trainer_of(*overrides: str) -> LocalTrainer:
    """A QMIX trainer on skirmish/3m, its process configured as an entry point does."""
    cfg = load_train_config("qmix", "skirmish/3m", [], [*SMALL, *overrides])
    configure(cfg.run)
    return LocalTrainer(cfg)


def train(*overrides: str) -> tuple[LocalTrainer, list]:
    trainer = trainer_of(*overrides)
    records: list = []
    trainer.train(on_eval=records.extend)
    return trainer, records


def figures(records: list) -> list[tuple]:
    return [(r.t_env, r.episode, r.test_return_mean, r.test_won_mean, r.updates) for r in records]


def test_acting_on_cpu_copies_gives_exactly_the_shared_modules_run():
    shared, shared_records = train("run.acting_weights=shared")
    copied, copied_records = train("run.acting_weights=copy")
    assert shared.worker.agent is shared.core.learner.agent
    for worker in (copied.worker, copied.core.evaluator.worker):
        assert worker.agent is not copied.core.learner.agent
        assert all(p.device.type == "cpu" for p in worker.agent.parameters())
    assert copied.core.learner.updates > 0
    assert figures(copied_records) == figures(shared_records)
    for (name, a), b in zip(
        shared.core.learner.agent.state_dict().items(),
        copied.core.learner.agent.state_dict().values(),
        strict=True,
    ):
        assert torch.equal(a, b), name


def test_a_copy_follows_the_learner_only_when_it_moves_on():
    trainer = trainer_of("run.acting_weights=copy")
    learning, worker = trainer.core.learning, trainer.worker
    learning.sync_worker(worker)
    assert worker.version == learning.learner.updates == 0
    with torch.no_grad():
        for p in learning.learner.agent.parameters():
            p.add_(1.0)  # the learner's weights change, its version does not
    learning.sync_worker(worker)
    first = next(iter(worker.agent.parameters()))
    assert not torch.equal(first, next(iter(learning.learner.agent.parameters())))
    learning.learner.updates += 1  # a new version: the copy loads it
    learning.sync_worker(worker)
    assert worker.version == 1
    for a, b in zip(worker.agent.parameters(), learning.learner.agent.parameters(), strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["run.device=gpu0"], "run: device 'gpu0' is not a torch device"),
        (
            ["run.device=cuda", "run.acting_weights=shared"],
            "acting_weights=shared needs device=cpu",
        ),
        (["run.acting_weights=mirror"], "run.acting_weights: 'mirror' is not one of"),
    ],
)
def test_bad_device_settings_name_the_key(overrides, message):
    with pytest.raises(ConfigError, match=message):
        load_train_config("qmix", "skirmish/3m", [], overrides)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error of a CUDA-less torch")
def test_a_cuda_learner_without_a_gpu_is_refused_naming_the_key():
    with pytest.raises(ConfigError, match=r"run\.device='cuda', but this torch sees no CUDA"):
        trainer_of("run.device=cuda")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_a_cuda_learner_trains_while_workers_act_on_cpu_copies(tmp_path):
    trainer, records = train("run.device=cuda")
    core = trainer.core
    assert core.learning.acting_weights == "copy"
    assert all(p.device.type == "cuda" for p in core.learner.agent.parameters())
    assert core.learner.updates > 0 and records
    for worker in (trainer.worker, core.evaluator.worker):
        core.learning.sync_worker(worker)
        for a, b in zip(worker.agent.parameters(), core.learner.agent.parameters(), strict=True):
            assert a.device.type == "cpu" and torch.equal(a, b.cpu())
    trainer.save(tmp_path / "checkpoint")  # a cuda checkpoint restores on a CPU learner
    cpu = trainer_of()
    cpu.restore(tmp_path / "checkpoint")
    assert cpu.core.learner.updates == core.learner.updates

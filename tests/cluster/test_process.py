"""`cluster.process.configure`: a training process's global settings are made at its entry
point, and building a trainer leaves them alone."""

from __future__ import annotations

import pytest
import torch

from cluster import process
from cluster.config.train import load_train_config
from cluster.launch.local import LocalTrainer


@pytest.fixture
def keep_torch_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def _weights(trainer: LocalTrainer) -> list[torch.Tensor]:
    return [p.detach().clone() for p in trainer.core.learner.agent.parameters()]


def test_configure_sets_threads_and_seed_and_a_trainer_touches_neither(keep_torch_threads):
    cfg = load_train_config("vdn", "matrix/two_step", [], ["run.torch_threads=2", "run.seed=3"])
    process.configure(cfg.run)
    assert torch.get_num_threads() == 2 and process.threads_used() == [2]
    first = _weights(LocalTrainer(cfg))
    torch.set_num_threads(1)
    torch.manual_seed(99)
    other = _weights(LocalTrainer(cfg))  # built without configure: nothing reset
    assert torch.get_num_threads() == 1
    assert any(not torch.equal(a, b) for a, b in zip(first, other, strict=True))
    process.configure(cfg.run)  # the same run's settings again: the same initial weights
    again = _weights(LocalTrainer(cfg))
    assert torch.get_num_threads() == 2
    assert all(torch.equal(a, b) for a, b in zip(first, again, strict=True))

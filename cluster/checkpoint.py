"""Checkpoint folders (`Checkpointer`): written atomically, read back on any device, and the
process's global random states they carry."""

from __future__ import annotations

import os
import random
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from cluster.config.train import TrainConfig

LEARNER_FILE, TRAINER_FILE, CONFIG_FILE = "learner.pt", "trainer.pt", "config.yaml"


def checkpoint_folder(path: Path) -> Path:
    """The folder holding the checkpoint written to `path`: `path`, or its `.old` copy after
    a crash between the two renames of `Checkpointer.write`."""
    path = Path(path)
    old = path.with_name(path.name + ".old")
    if not (path / TRAINER_FILE).exists() and (old / TRAINER_FILE).exists():
        return old
    return path


def global_rng_state() -> dict[str, Any]:
    """torch's, numpy's and python's global random states."""
    return {
        "torch_rng": torch.get_rng_state(),
        "numpy_rng": np.random.get_state(),
        "python_rng": random.getstate(),
    }


def set_global_rng_state(state: dict[str, Any]) -> None:
    """Restore `global_rng_state` (checkpoints of earlier commits hold torch's only)."""
    torch.set_rng_state(state["torch_rng"])
    if "numpy_rng" in state:
        np.random.set_state(state["numpy_rng"])
        random.setstate(state["python_rng"])


class Checkpointer:
    """Writes and reads a run's checkpoint folders: the learner's state (learner.pt), the
    trainer's (trainer.pt: counters, random states, the loop's state) and the config.

    Args:
        cfg: the run (its config is written beside the states; its device loads them).
        folder: where the loop checkpoints every run.save_interval env steps (None: never).
    """

    def __init__(self, cfg: TrainConfig, folder: Path | None) -> None:
        self.cfg, self.folder = cfg, folder

    def write(
        self,
        path: Path,
        learner_state: dict,
        state: dict,
        files: Callable[[Path], None] | None = None,
    ) -> None:
        """Write the states to `path` atomically: a crash mid-write leaves the previous
        checkpoint (or its `.old` copy) intact.

        Args:
            path: the checkpoint folder.
            learner_state: the learner's `state_dict`.
            state: the trainer's state.
            files: writes more files into the folder being built (e.g. buffer tables).
        """
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        torch.save(learner_state, tmp / LEARNER_FILE)
        torch.save(state, tmp / TRAINER_FILE)
        (tmp / CONFIG_FILE).write_text(yaml.safe_dump(self.cfg.to_yaml_dict(), sort_keys=False))
        if files:
            files(tmp)
        old = path.with_name(path.name + ".old")
        shutil.rmtree(old, ignore_errors=True)
        if path.exists():
            os.replace(path, old)
        os.replace(tmp, path)
        shutil.rmtree(old, ignore_errors=True)

    def read(self, path: Path) -> tuple[dict, dict]:
        """(the learner's state on run.device, the trainer's state) from the checkpoint at
        `path` (or its `.old` copy)."""
        path = checkpoint_folder(path)
        device = self.cfg.run.device  # a checkpoint saved on another device loads here
        learner_state = torch.load(path / LEARNER_FILE, weights_only=False, map_location=device)
        state = torch.load(path / TRAINER_FILE, weights_only=False, map_location="cpu")
        return learner_state, state

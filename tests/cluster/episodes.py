"""Reading the episodes a run left in its buffer folders, for comparing the two modes."""

from pathlib import Path

import numpy as np

from buffer_service.config import BufferConfig, TableConfig
from buffer_service.state import BufferState
from buffer_service.storage import Storage

FIELDS = ("obs", "state", "avail_actions", "actions", "reward", "terminated")


def actor0_episodes(folder: Path) -> list:
    """Every episode of actor 0 stored in a snapshot folder (a buffer service's, or a local
    checkpoint's buffer/member-0), in the order it was collected."""
    state = BufferState(
        BufferConfig(tables=(TableConfig(name="replay", kind="replay", capacity=100000),))
    )
    Storage(str(folder), read_only=True).restore(state)
    return [state.episodes[k] for k in sorted(state.episodes) if k[0] == 0]


def assert_same_first_episodes(local_folder: Path, cluster_folder: Path, at_least: int) -> None:
    """The episodes acted with the initial weights (policy_version 0) are the same, field by
    field, in both folders, and there are at least `at_least` of them in each."""
    local = [ep for ep in actor0_episodes(local_folder) if ep.policy_version == 0]
    remote = [ep for ep in actor0_episodes(cluster_folder) if ep.policy_version == 0]
    n = min(len(local), len(remote))
    assert n >= at_least, (len(local), len(remote))
    for k, (a, b) in enumerate(zip(local[:n], remote[:n], strict=True)):
        for name in FIELDS:
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), f"{k} {name}")

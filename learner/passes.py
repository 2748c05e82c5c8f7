"""An update's batch in passes of episodes of similar length, whose gradients add up to the
batch's: the same update with a bounded working set.

A value-family or RDN update keeps its forward graph until the backward; on bane_vs_bane
(24 agents, episodes up to 200 steps, 3 seeds of 32 episodes) that graph held about 1 GB,
and the learner's heap kept its peak (`run.keep_freed_memory`). `episode_passes` splits a
`TensorBatch` into passes of at most `max_rows` agent-steps (members x episodes x steps x
agents, padding included). Each member's episodes are sorted by length first, so a pass of
short episodes is padded only to the longest of them, not to the batch's longest: fewer
padded steps to compute as well as fewer bytes.

Every loss of these learners is a per-member mean over the real entries of the whole batch
(`masked_mean`). Split into passes it is a sum of per-pass parts that keep the whole batch's
denominator (`masked_part`): backpropagating each part in turn accumulates the whole batch's
gradient, up to the order of float additions. Nothing in these losses couples two episodes
(the agents' recurrence, the critic and mixer, and the Q(lambda) targets are per episode;
reward normalisation, which updates running statistics, is applied once to the whole batch
before it is split).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

import torch

from learner.batch import TensorBatch

# The default `update_pass_rows` of the value family and RDN (their config docstrings).
UPDATE_PASS_ROWS = 32768


def validate_pass_rows(rows: int) -> None:
    """`update_pass_rows` must be 0 (one pass) or positive."""
    if rows < 0:
        raise ValueError(f"update_pass_rows must be >= 0 (0: one pass), got {rows}")


def episode_lengths(tb: TensorBatch) -> torch.Tensor:
    """Real transitions of every episode, [E, B] long (the mask is 1 on a prefix)."""
    return tb.mask.sum(-1).round().long()


def pass_plan(lengths: torch.Tensor, n_agents: int, max_rows: int) -> list[tuple[int, int]]:
    """Position ranges [lo, hi) of each member's episodes sorted by length, one per pass.

    A pass of positions lo .. hi-1 is padded to the longest of those episodes over all
    members (`lengths` sorted along B, [E, B]) and holds E * (hi - lo) * (T + 1) * N rows;
    a pass takes episodes while that stays within `max_rows`, and at least one.
    `max_rows` <= 0: one pass.
    """
    e, b = lengths.shape
    if max_rows <= 0 or b == 0:
        return [(0, b)]
    longest = lengths.amax(0).tolist()  # non-decreasing: each member's lengths are sorted
    plan, lo = [], 0
    for hi in range(1, b + 1):
        if hi - 1 > lo and e * (hi - lo) * (longest[hi - 1] + 1) * n_agents > max_rows:
            plan.append((lo, hi - 1))
            lo = hi - 1
    plan.append((lo, b))
    return plan


def episode_passes(tb: TensorBatch, max_rows: int) -> EpisodePasses:
    """`tb` as passes of at most `max_rows` agent-steps each (`pass_plan`), each member's
    episodes taken shortest first and each pass cut to its own longest episode; one pass,
    `tb` itself, when it fits (or max_rows <= 0).

    Every episode of every member is in exactly one pass, whole, and a pass holds the same
    number of episodes of every member. A pass's tensors are copied when the pass is taken
    (iterating), so a learner that iterates holds one pass's copy at a time.
    """
    return EpisodePasses(tb, max_rows)


class EpisodePasses:
    """The passes of `episode_passes`: `len()` of them, each built as it is iterated to."""

    def __init__(self, tb: TensorBatch, max_rows: int):
        e, b, t, n = tb.shape
        self.tb = tb
        if max_rows <= 0 or e * b * (t + 1) * n <= max_rows:
            self.order, self.lengths, self.plan = None, None, [(0, b)]
            return
        lengths = episode_lengths(tb)
        self.order = torch.argsort(lengths, dim=1, stable=True)  # [E, B]
        self.lengths = lengths.gather(1, self.order)
        self.plan = pass_plan(self.lengths, n, max_rows)

    def __len__(self) -> int:
        return len(self.plan)

    def __iter__(self) -> Iterator[TensorBatch]:
        if self.order is None:
            yield self.tb
            return
        for lo, hi in self.plan:
            yield self._take(lo, hi)

    def _take(self, lo: int, hi: int) -> TensorBatch:
        tb, t = self.tb, self.tb.shape[2]
        idx = self.order[:, lo:hi]
        member = torch.arange(idx.shape[0], device=idx.device).view(-1, 1)
        steps = max(int(self.lengths[:, lo:hi].max()), 1)
        fields = {}
        for f in dataclasses.fields(TensorBatch):
            v = getattr(tb, f.name)
            if v.dim() > 2:  # time-indexed: T+1 steps (obs, state, avail) or T
                v = v[:, :, : steps + (v.shape[2] - t)]
            fields[f.name] = v[member, idx]  # [E, hi - lo, ...], a contiguous copy
        return TensorBatch(**fields)

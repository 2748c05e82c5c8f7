"""The learner's batches in both modes: a main batch and, for E-CAC / EM-CAC, an extra batch
from a second table, either of which the tables' limiters may hold back."""

from __future__ import annotations

from collections.abc import Callable

from buffer_service.episode import EpisodeBatch
from cluster.config.plan import DataPlan

Sampler = Callable[[str, int], EpisodeBatch | None]
Ready = Callable[[str, int], bool]


class BatchPairer:
    """Pairs the main and extra batches without wasting a sample of either; `--mode local`
    (`cluster.launch.local.LocalData`) and `--mode cluster` (`ServiceData`) both take their
    batches through it.

    The main batch is sampled first and kept until its extra batch arrives, so a held-back
    extra sample never throws a main batch away (nor costs the cycling table's episodes one
    of their `max_times_sampled` samples). With `ready` (tables that can be asked whether
    they would serve a sample, as the in-process tables can), nothing is sampled until both
    tables would serve theirs, so no batch waits from one call to the next; the buffer
    service can only be asked by sampling, and a main batch may wait there.

    Calling loop::

        pairer = BatchPairer(plan, sample)      # sample(table, n) -> EpisodeBatch | None
        pair = pairer.next()
        if pair is not None:
            learner.step(*pair)
    """

    def __init__(self, plan: DataPlan, sample: Sampler, ready: Ready | None = None):
        self.plan, self.sample, self.ready = plan, sample, ready
        self.pending: EpisodeBatch | None = None  # a main batch waiting for its extra batch
        self.wanted = [(plan.table, plan.batch_size)]
        if plan.extra_table:
            self.wanted.append((plan.extra_table, plan.extra_batch_size))

    def next(self) -> tuple[EpisodeBatch, EpisodeBatch | None] | None:
        """The next (main, extra) pair (extra None without an extra table), or None."""
        needed = self.wanted if self.pending is None else self.wanted[1:]
        if self.ready is not None and not all(self.ready(t, n) for t, n in needed):
            return None
        if self.pending is None:
            self.pending = self.sample(*self.wanted[0])
            if self.pending is None:
                return None
        extra = None
        if len(self.wanted) > 1:
            extra = self.sample(*self.wanted[1])
            if extra is None:
                return None  # the main batch waits for it
        batch, self.pending = self.pending, None
        return batch, extra

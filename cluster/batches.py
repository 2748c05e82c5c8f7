"""The learner's batches in `--mode cluster`: a main batch and, for E-CAC / EM-CAC, an extra
batch from a second table, each of which the buffer service's limiter may hold back."""

from __future__ import annotations

from collections.abc import Callable

from buffer_service.episode import EpisodeBatch
from cluster.config.plan import DataPlan

Sampler = Callable[[str, int], EpisodeBatch | None]


class BatchPairer:
    """Pairs the main and extra batches without wasting a sample of either.

    The extra batch is sampled first and kept until a main batch arrives. A main batch is
    requested only once an extra batch is in hand, so a held-back extra sample never costs
    the cycling table's episodes one of their `max_times_sampled` samples, and a held-back
    main sample never throws the extra batch away.

    Calling loop::

        pairer = BatchPairer(plan, sample)      # sample(table, n) -> EpisodeBatch | None
        pair = pairer.next()
        if pair is not None:
            learner.step(*pair)
    """

    def __init__(self, plan: DataPlan, sample: Sampler):
        self.plan, self.sample = plan, sample
        self.pending: EpisodeBatch | None = None  # an extra batch waiting for its main batch

    def next(self) -> tuple[EpisodeBatch, EpisodeBatch | None] | None:
        plan = self.plan
        if plan.extra_table and self.pending is None:
            self.pending = self.sample(plan.extra_table, plan.extra_batch_size)
            if self.pending is None:
                return None
        batch = self.sample(plan.table, plan.batch_size)
        if batch is None:
            return None
        extra, self.pending = self.pending, None
        return batch, extra

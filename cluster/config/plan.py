"""The data plan of a training run: which buffer tables it needs, the learner's batch sizes and
the replay ratio the rate limiters enforce, derived from its `TrainConfig`."""

from __future__ import annotations

from dataclasses import dataclass, replace

from buffer_service.config import RateLimiterConfig, TableConfig
from cluster.config.train import TrainConfig
from learner.registry import get_algo


@dataclass(frozen=True)
class DataPlan:
    """Which buffer tables a run needs and what one learner step consumes from them.

    Attributes:
        tables: the tables to create (in process or in the buffer service).
        table: the table of the main batch; batch_size its size.
        updates_per_episode: learner steps per inserted episode (per ensemble member).
        extra_table: a second batch's table (E-CAC's off-policy critic pass), or None.
        extra_batch_size: that batch's size.
        store_state: whether the tables keep the episodes' state (the learner reads it).
    """

    tables: tuple[TableConfig, ...]
    table: str
    batch_size: int
    updates_per_episode: float
    extra_table: str | None = None
    extra_batch_size: int = 0
    store_state: bool = True


def data_plan(cfg: TrainConfig, actors: int = 1) -> DataPlan:
    """Tables and batches for `cfg`'s algorithm family.

    Every table keeps the state only when the algorithm reads it (`AlgoSpec.reads_state`).
    value family: `replay` (replay.capacity within replay.max_mib), batches of replay.batch_size,
        replay.updates_per_episode learner steps per inserted episode.
    policy gradient, on-policy (cac, mcac, coma): `cycling` holding exactly the newest
        run.num_envs episodes, each used once: one step per round of run.num_envs episodes.
    policy gradient, extended (ecac, emcac): `cycling` of cycling.capacity episodes, each
        used capacity / num_envs times, plus a `replay` batch for the extra critic pass.
    Every table gets a sample-to-insert limiter at that ratio, so `--mode cluster` keeps the
    same update-to-data ratio as a one-process run; `actors` x cluster.rate_slack rounds may
    be in flight.
    """
    spec = get_algo(cfg.algo_name)
    n_new = cfg.run.num_envs
    slack = actors * cfg.cluster.rate_slack * n_new
    rp = cfg.replay

    def limiter(spi: float, min_size: int, batch: int) -> RateLimiterConfig:
        return RateLimiterConfig(
            min_size_to_sample=min_size,
            samples_per_insert=spi,
            error_buffer=max(batch, spi * slack),
        )

    bs = rp.batch_size
    value = spec.family == "value"
    replay_spi = bs * rp.updates_per_episode if value else bs / n_new
    replay = TableConfig(
        name="replay",
        kind="replay",
        capacity=rp.capacity,
        max_bytes=int(rp.max_mib * 2**20),
        replacement=rp.with_replacement,
        rate_limiter=limiter(replay_spi, bs, bs),
    )
    state = spec.reads_state(cfg.algo)
    if value:
        return DataPlan((replay,), "replay", bs, rp.updates_per_episode, store_state=state)
    capacity = cfg.cycling.capacity if spec.extended else n_new
    cycling_limiter = limiter(capacity / n_new, capacity, capacity)
    if spec.extended and bs > capacity:
        # No step until the replay table also holds a batch: the cycling table's inserts of
        # that joint warm-up must pass its limiter, or actors and learner would wait on each
        # other forever (and local mode would stop with RateLimitDeadlockError).
        warmup = cycling_limiter.samples_per_insert * (bs - capacity)
        cycling_limiter = replace(
            cycling_limiter, error_buffer=cycling_limiter.error_buffer + warmup
        )
    cycling = TableConfig(
        name="cycling",
        kind="cycling",
        capacity=capacity,
        max_times_sampled=max(1, capacity // n_new),
        rate_limiter=cycling_limiter,
    )
    if not spec.extended:
        return DataPlan((cycling,), "cycling", capacity, 1 / n_new, store_state=state)
    return DataPlan((cycling, replay), "cycling", capacity, 1 / n_new, "replay", bs, state)

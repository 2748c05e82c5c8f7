"""The one batch pairer of both modes (`cluster.batches.BatchPairer`): E-CAC / EM-CAC's main
(cycling) batch and extra (replay) batch, over the buffer service's own tables in process."""

from buffer_service.local import LocalBuffer
from cluster.batches import BatchPairer
from cluster.config.plan import data_plan
from cluster.config.train import load_train_config
from tests.learner.test_pg_data import _episode, _seqs


def _limited(buf: LocalBuffer):
    """The service's sample: None while the table's limiter holds the batch back."""

    def sample(table: str, n: int):
        return buf.sample(table, n) if buf.ready(table, n) else None

    return sample


def _samples(buf: LocalBuffer, table: str) -> int:
    """Episodes sampled from `table` so far (the limiter counts items, not requests)."""
    return buf.stats()["tables"][table]["samples"]


def _emcac():
    plan = data_plan(load_train_config("emcac", "skirmish/3m"))
    return plan, LocalBuffer(plan.tables, seed=0)


def test_a_held_back_extra_batch_keeps_the_main_batch_for_the_next_call():
    plan, buf = _emcac()
    pairer = BatchPairer(plan, _limited(buf))
    buf.insert([_episode(s) for s in range(32)], tables=["cycling"])
    assert pairer.next() is None  # replay not ready: the cycling batch is taken and kept
    assert _samples(buf, "cycling") == 32
    buf.insert([_episode(s) for s in range(100, 132)], tables=["replay"])
    batch, extra = pairer.next()
    assert _seqs(batch) == list(range(32)) and set(_seqs(extra)) <= set(range(100, 132))
    assert _samples(buf, "cycling") == 32 and _samples(buf, "replay") == 32  # no second sample


def test_a_held_back_main_batch_leaves_the_extra_table_untouched():
    plan, buf = _emcac()
    pairer = BatchPairer(plan, _limited(buf))
    buf.insert([_episode(s) for s in range(32)], tables=["replay"])
    assert pairer.next() is None
    assert _samples(buf, "replay") == 0
    buf.insert([_episode(s) for s in range(100, 132)], tables=["cycling"])
    batch, extra = pairer.next()
    assert _seqs(batch) == list(range(100, 132)) and set(_seqs(extra)) <= set(range(32))


def test_with_ready_nothing_is_sampled_until_both_tables_can_serve():
    plan, buf = _emcac()
    pairer = BatchPairer(plan, _limited(buf), buf.ready)
    buf.insert([_episode(s) for s in range(32)], tables=["cycling"])
    assert pairer.next() is None and pairer.pending is None
    assert _samples(buf, "cycling") == 0  # local mode: no batch waits across calls
    buf.insert([_episode(s) for s in range(100, 132)], tables=["replay"])
    batch, extra = pairer.next()
    assert _seqs(batch) == list(range(32)) and set(_seqs(extra)) <= set(range(100, 132))


def test_an_on_policy_plan_samples_one_table():
    plan = data_plan(load_train_config("cac", "skirmish/3m"))
    buf = LocalBuffer(plan.tables, seed=0)
    pairer = BatchPairer(plan, _limited(buf))
    assert pairer.next() is None
    buf.insert([_episode(s) for s in range(4)])
    batch, extra = pairer.next()
    assert _seqs(batch) == [0, 1, 2, 3] and extra is None

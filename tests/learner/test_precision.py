"""`run.precision`: bfloat16 autocast for the learner's updates, detected at run time."""

import pytest
import torch

from cluster.bench.update import record_batch
from cluster.config.train import load_train_config
from cluster.core import TrainerCore
from cluster.process import configure
from learner import precision
from learner.precision import cpu_has_bf16, cpu_model_and_flags, effective_precision

CPU = torch.device("cpu")


def test_flags_are_read_from_cpuinfo(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor : 0\nflags : fpu sse avx512f avx512_bf16 amx_tile\n")
    assert cpu_has_bf16(info)
    info.write_text("processor : 0\nflags : fpu sse avx512f\n")
    assert not cpu_has_bf16(info)
    assert not cpu_has_bf16(tmp_path / "missing")


def test_bf16_falls_back_to_float32_where_the_cpu_lacks_it(monkeypatch):
    monkeypatch.setattr(precision, "cpu_has_bf16", lambda: False)
    assert effective_precision("bf16", CPU) == "float32"
    assert effective_precision("float32", CPU) == "float32"
    monkeypatch.setattr(precision, "cpu_has_bf16", lambda: True)
    assert effective_precision("bf16", CPU) == "bf16"
    with pytest.raises(ValueError, match="precision"):
        effective_precision("float16", CPU)


def test_config_refuses_an_unknown_precision():
    with pytest.raises(Exception, match="precision"):
        load_train_config("vdn", "skirmish/3m", [], ["run.precision=half"])


def one_update(algo: str, prec: str, batch) -> tuple[dict, torch.Tensor, torch.Tensor]:
    """(metrics, the agent's float32 weights flattened before and after one update)."""
    cfg = load_train_config(algo, "skirmish/3m", [], [f"run.precision={prec}"])
    configure(cfg.run)
    core = TrainerCore(cfg, 2)
    assert core.learning.precision == prec

    def flat() -> torch.Tensor:
        params = list(core.learner.agent.parameters())
        assert all(p.dtype == torch.float32 for p in params)
        return torch.cat([p.detach().reshape(-1) for p in params])

    before = flat()
    metrics = core.update(batch, None)
    return metrics, before, flat()


@pytest.mark.skipif(not cpu_has_bf16(), reason="this CPU has no AVX512-BF16 / AMX-BF16")
@pytest.mark.parametrize("algo", ["vdn", "qmix", "rdn"])
def test_a_bf16_update_is_close_to_the_float32_one_and_keeps_float32_weights(algo):
    batch = record_batch("skirmish/3m", 4, 2)
    m32, start32, end32 = one_update(algo, "float32", batch)
    m16, start16, end16 = one_update(algo, "bf16", batch)
    assert torch.equal(start16, start32)  # the same seeded initial weights
    for key, value in m32.items():
        assert m16[key] == pytest.approx(value, rel=0.05, abs=0.02), key
    # Adam's first step is about lr * sign(gradient) for every weight, so compare directions
    cos = torch.nn.functional.cosine_similarity(end16 - start16, end32 - start32, dim=0)
    assert cos > 0.9


@pytest.mark.skipif(not cpu_has_bf16(), reason="this CPU has no AVX512-BF16 / AMX-BF16")
@pytest.mark.parametrize("algo", ["iql", "qmix_ns", "cac", "ecac", "mcac", "emcac", "coma"])
def test_every_other_algorithm_updates_under_bf16(algo):
    batch = record_batch("skirmish/3m", 4, 2)
    metrics, _, _ = one_update(algo, "bf16", batch)
    assert all(torch.isfinite(torch.tensor(v)) for v in metrics.values())


def test_cpu_model_and_flags_reads_the_first_cpu(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text(
        "processor\t: 0\nmodel name\t: AMD EPYC 9R14\nflags\t\t: fpu avx2 avx512f avx512_bf16\n\n"
        "processor\t: 1\nmodel name\t: other\nflags\t\t: fpu\n"
    )
    model, flags = cpu_model_and_flags(info)
    assert model == "AMD EPYC 9R14"
    assert {"avx2", "avx512f", "avx512_bf16"} <= flags and "amx_bf16" not in flags
    assert cpu_model_and_flags(tmp_path / "missing") == ("", set())

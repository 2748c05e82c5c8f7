"""What every benchmark's JSON says about the machine that made it."""

from cluster.bench.common import cpu_info, machine


def test_cpu_info_names_the_model_and_the_flags_that_change_timings(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("model name\t: Intel(R) Xeon(R)\nflags\t\t: fpu avx2 avx512f amx_bf16 sse\n")
    assert cpu_info(info) == {
        "cpu_model": "Intel(R) Xeon(R)",
        "cpu_flags": ["avx2", "avx512f", "amx_bf16"],
    }
    assert cpu_info(tmp_path / "missing") == {"cpu_model": "unknown", "cpu_flags": []}


def test_machine_carries_the_cpu():
    got = machine()
    assert {"cpu_model", "cpu_flags", "cpus", "torch"} <= set(got)

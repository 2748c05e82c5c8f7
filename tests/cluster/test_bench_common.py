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


def test_machine_carries_how_openmp_threads_wait(monkeypatch):
    monkeypatch.setenv("GOMP_SPINCOUNT", "1000")
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert machine()["openmp_env"] == {
        "OMP_WAIT_POLICY": "ACTIVE",
        "GOMP_SPINCOUNT": "1000",
        "OMP_NUM_THREADS": None,
    }

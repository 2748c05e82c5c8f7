"""`scaling.png` of `credit bench scaling`: throughput and efficiency against actor count."""

from __future__ import annotations

from pathlib import Path
from typing import Any

LABELS = {
    "insert": "training: inserted",
    "learner": "training: consumed by the learner",
    "no_learner_insert": "bound: no learner (untrained policy)",
    "transport_insert": "bound: transport, inserted (no env)",
    "transport_sample": "bound: transport, sampled (no training)",
}
STYLES = {
    "insert": "o-",
    "learner": "s-",
    "no_learner_insert": "^--",
    "transport_insert": "v:",
    "transport_sample": "d:",
}


def plot(figures: dict[str, Any], path: Path) -> None:
    """Two panels: env steps/s (log scale) and efficiency T(N)/(N·T(1)) against actors.

    Args:
        figures: the benchmark's figures (`throughput_env_steps_per_s`, `efficiency`, env).
        path: the PNG to write.
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    fig, (ax_t, ax_e) = plt.subplots(1, 2, figsize=(12, 4.5))
    for name, series in figures["throughput_env_steps_per_s"].items():
        ns = sorted(series, key=int)
        ax_t.plot(ns, [series[n] for n in ns], STYLES[name], label=LABELS[name])
    for name, series in figures["efficiency"].items():
        ns = sorted(series, key=int)
        ys = [series[n] for n in ns]
        ax_e.plot(ns, [y if y is not None else float("nan") for y in ys], STYLES[name])
    counts = figures["actors"]
    ax_e.axhline(1.0, color="grey", lw=0.8)
    ax_t.set(xlabel="rollout actors", ylabel="env steps / s (median of windows)", yscale="log")
    ax_e.set(xlabel="rollout actors", ylabel="efficiency T(N) / (N · T(1))", ylim=(0, 1.2))
    for ax in (ax_t, ax_e):
        ax.set_xticks(counts)
        ax.grid(alpha=0.3)
    ax_t.legend(fontsize=8)
    cpus = figures.get("ray_num_cpus")
    fig.suptitle(
        f"credit bench scaling: {figures['algo']} on {figures['env']}, {cpus} CPUs, "
        f"fsync {'on' if figures.get('fsync') else 'off'}"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

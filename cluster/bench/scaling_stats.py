"""Pure parts of `credit bench scaling`: /proc CPU accounting, per-window figures from two
snapshots of the running system, medians over windows and scaling efficiency.

Nothing here starts processes or imports Ray, so it is tested with hand-computed values.

A snapshot is a plain dict taken between windows (see `cluster.bench.scaling.Probe`)::

    {
        "t": monotonic seconds,
        "t_env": env steps the coordinator counted (inserted rounds),
        "episodes": episodes the coordinator counted,
        "learner": LoopStats.snapshot() of the learner (or the transport bound's sampler),
        "buffer": the buffer service's stats() (tables, limiter_waits),
        "actors": [RolloutActor.stats(), ...],
        "cpu_ticks": {"learner": ticks, "buffer": ticks, "actors": ticks, "ray_system": ticks},
        "machine_ticks": (busy, total) from /proc/stat,
    }
"""

from __future__ import annotations

import os
import statistics
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

CPU_GROUPS = ("learner", "buffer", "actors", "ray_system")


def parse_proc_stat(text: str) -> tuple[int, int]:
    """(ppid, utime + stime) from the text of /proc/<pid>/stat.

    The command name (field 2) is in parentheses and may hold spaces or parentheses, so the
    fields are counted after its last ')': state is then field 3, ppid 4, utime 14, stime 15.

    Args:
        text: the file's content.

    Returns:
        (ppid, CPU time in clock ticks spent in user and kernel mode).
    """
    rest = text[text.rindex(")") + 2 :].split()
    # rest[0] is field 3 (state), so field k is rest[k - 3].
    return int(rest[1]), int(rest[11]) + int(rest[12])


def parse_machine_stat(text: str) -> tuple[int, int]:
    """(busy, total) clock ticks of all CPUs from the `cpu` line of /proc/stat.

    Args:
        text: the content of /proc/stat.

    Returns:
        busy = total - idle - iowait, and total = the sum of every field of the line.
    """
    for line in text.splitlines():
        if line.startswith("cpu "):
            values = [int(v) for v in line.split()[1:]]
            idle = values[3] + (values[4] if len(values) > 4 else 0)
            total = sum(values[:8])  # guest time is already counted in user/nice
            return total - idle, total
    raise ValueError("no aggregate 'cpu' line in /proc/stat")


def process_table(proc: Path = Path("/proc")) -> dict[int, tuple[int, int]]:
    """pid -> (ppid, utime + stime ticks) for every process readable now."""
    table = {}
    for entry in proc.iterdir():
        if not entry.name.isdigit():
            continue
        try:
            table[int(entry.name)] = parse_proc_stat((entry / "stat").read_text())
        except (OSError, ValueError, IndexError):
            continue  # exited while we looked
    return table


def descendants(table: Mapping[int, tuple[int, int]], root: int) -> set[int]:
    """Every pid below `root` in the process tree of `table` (root excluded)."""
    children: dict[int, list[int]] = {}
    for pid, (ppid, _) in table.items():
        children.setdefault(ppid, []).append(pid)
    found: set[int] = set()
    stack = [root]
    while stack:
        for child in children.get(stack.pop(), []):
            if child not in found:
                found.add(child)
                stack.append(child)
    return found


def group_ticks(
    table: Mapping[int, tuple[int, int]],
    learner: int,
    buffer: int | None,
    actors: Iterable[int],
) -> dict[str, int]:
    """CPU ticks per group: the learner process itself, the buffer service, the rollout
    actors, and every other descendant of the learner (Ray's GCS, raylet, idle workers).

    Args:
        table: `process_table()`.
        learner: pid of this (driver and learner) process.
        buffer: pid of the buffer service, or None.
        actors: pids of the actor processes.

    Returns:
        {"learner", "buffer", "actors", "ray_system"} -> ticks (0 for pids that are gone).
    """
    actors = set(actors)
    named = {learner, *actors} | ({buffer} if buffer else set())

    def ticks(pids: Iterable[int]) -> int:
        return sum(table[p][1] for p in pids if p in table)

    return {
        "learner": ticks([learner]),
        "buffer": ticks([buffer] if buffer else []),
        "actors": ticks(actors),
        "ray_system": ticks(descendants(table, learner) - named),
    }


def lag_summary(counts: Mapping[int, int]) -> dict[str, float | None]:
    """Mean and 95th percentile (nearest rank) of a lag histogram {lag: episodes}.

    Returns:
        {"mean": ..., "p95": ..., "episodes": n}; mean and p95 are None when n is 0.
    """
    n = sum(counts.values())
    if n == 0:
        return {"mean": None, "p95": None, "episodes": 0}
    mean = sum(lag * c for lag, c in counts.items()) / n
    rank = max(1, -(-95 * n // 100))  # ceil(0.95 n)
    seen = 0
    for lag in sorted(counts):
        seen += counts[lag]
        if seen >= rank:
            return {"mean": mean, "p95": float(lag), "episodes": n}
    raise AssertionError("unreachable")


def counts_delta(new: Mapping[Any, int], old: Mapping[Any, int]) -> dict[int, int]:
    """new - old of two cumulative histograms (keys as ints; JSON may have made them str)."""
    out = {int(k): v - old.get(k, old.get(str(k), 0)) for k, v in new.items()}
    return {k: v for k, v in out.items() if v}


def _rate(new: float, old: float, dt: float) -> float:
    return (new - old) / dt


def _waits(new: Mapping, old: Mapping, op: str, dt: float) -> dict[str, float]:
    a, b = new["limiter_waits"][op], old["limiter_waits"][op]
    return {
        "held_per_s": _rate(a["count"], b["count"], dt),
        "held_fraction_of_time": _rate(a["seconds"], b["seconds"], dt),
        "timeouts": a["timeouts"] - b["timeouts"],
    }


def _actor_split(new: list[dict], old: list[dict], dt: float) -> dict[str, float]:
    """Fraction of the actors' wall time (summed over actors) per phase of their loop."""
    before = {a["pid"]: a for a in old}
    total = {"act_s": 0.0, "insert_s": 0.0, "sync_s": 0.0, "insert_refusals": 0}
    for a in new:
        b = before.get(a["pid"], {k: 0 for k in total})  # a restarted actor starts at 0
        for k in total:
            total[k] += a[k] - b[k]
    wall = dt * max(1, len(new))
    return {
        "acting_fraction": total["act_s"] / wall,
        "inserting_fraction": total["insert_s"] / wall,
        "ray_sync_fraction": total["sync_s"] / wall,
        "insert_refusals": total["insert_refusals"],
    }


def window_figures(old: Mapping, new: Mapping, clk_tck: int, ncpu: int) -> dict[str, Any]:
    """The figures of one window between two snapshots (see the module docstring).

    Args:
        old, new: snapshots at the window's start and end.
        clk_tck: clock ticks per second (os.sysconf("SC_CLK_TCK")).
        ncpu: CPUs of the machine, to turn /proc/stat's fractions into cores.

    Returns:
        Rates per second of wall time, cores used per group, buffer depth at the end,
        policy lag, rate-limiter waits and the actors' time split.
    """
    dt = new["t"] - old["t"]
    ln, lo = new["learner"], old["learner"]
    cores = {g: (new["cpu_ticks"][g] - old["cpu_ticks"][g]) / clk_tck / dt for g in CPU_GROUPS}
    cores["total"] = sum(cores.values())
    busy = new["machine_ticks"][0] - old["machine_ticks"][0]
    total = new["machine_ticks"][1] - old["machine_ticks"][1]
    cores["machine_busy"] = ncpu * busy / total if total else 0.0
    cores["others"] = max(0.0, cores["machine_busy"] - cores["total"])
    tables = new["buffer"]["tables"]
    sample_requests = ln["sample_requests"] - lo["sample_requests"]
    inserted = new["t_env"] - old["t_env"]
    return {
        "seconds": dt,
        "insert_env_steps_per_s": _rate(new["t_env"], old["t_env"], dt),
        "insert_episodes_per_s": _rate(new["episodes"], old["episodes"], dt),
        "learner_env_steps_per_s": _rate(ln["consumed_env_steps"], lo["consumed_env_steps"], dt),
        "updates_per_s": _rate(ln["updates"], lo["updates"], dt),
        "sample_requests_per_s": sample_requests / dt,
        "learner_time": {
            "sampling_fraction": _rate(ln["sample_s"], lo["sample_s"], dt),
            "updating_fraction": _rate(ln["update_s"], lo["update_s"], dt),
            "publishing_fraction": _rate(ln["publish_s"], lo["publish_s"], dt),
        },
        "learner_sample_timeouts": ln["sample_timeouts"] - lo["sample_timeouts"],
        "cpu_cores": cores,
        # CPU time per inserted env step: steadier than rates on a shared machine.
        "cpu_ms_per_inserted_step": {
            g: (1000.0 * cores[g] * dt / inserted if inserted else None)
            for g in (*CPU_GROUPS, "total")
        },
        "buffer_size": {name: t["size"] for name, t in tables.items()},
        "policy_lag": lag_summary(counts_delta(ln["lag_counts"], lo["lag_counts"])),
        "limiter": {
            "insert": _waits(new["buffer"], old["buffer"], "insert", dt),
            "sample": _waits(new["buffer"], old["buffer"], "sample", dt),
        },
        "actors": _actor_split(new["actors"], old["actors"], dt),
    }


def median_tree(windows: list[Any]) -> Any:
    """The median of every numeric leaf across windows of the same nested shape.

    Leaves that are None in some windows are taken over the others (None if all are).
    """
    first = windows[0]
    if isinstance(first, Mapping):
        return {k: median_tree([w[k] for w in windows]) for k in first}
    values = [w for w in windows if w is not None]
    if not values:
        return None
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
        return statistics.median(values)
    return first


def efficiency(throughput: Mapping[int, float]) -> dict[int, float | None]:
    """Scaling efficiency T(N) / (N/N0 · T(N0)) against the smallest actor count N0 (with
    N0 = 1 this is the usual T(N) / (N · T(1))).

    Args:
        throughput: actor count -> throughput (env steps/s).

    Returns:
        actor count -> efficiency (None where T(N0) is 0).
    """
    n0 = min(throughput)
    base = throughput[n0]
    return {n: (t * n0 / (n * base) if base else None) for n, t in sorted(throughput.items())}


def rounded(obj: Any, digits: int = 4) -> Any:
    """`obj` with every float rounded to `digits` significant decimals (for the JSON)."""
    if isinstance(obj, float):
        return float(f"{obj:.{digits}g}")
    if isinstance(obj, Mapping):
        return {k: rounded(v, digits) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [rounded(v, digits) for v in obj]
    return obj


def cpu_count() -> int:
    """CPUs this process may run on (the affinity mask; os.cpu_count as a fallback)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1

"""How a credit process shares the CPU with the others on its machine.

Two settings, each made once per process:

* **Threads that sleep when idle.** torch's CPU wheel runs its intra-op threads on GNU
  OpenMP, whose default lets every thread spin for a while after each parallel region. On a
  machine where other processes want the cores, the spinning threads take CPU from them,
  and a thread descheduled in turn holds up every region that waits for it: beside one busy
  loop on the 2-core machine, 10k env steps of `credit bench learn` on two threads did not
  finish in 400 s against 8.4 s alone. `prefer_sleeping_threads` sets
  OMP_WAIT_POLICY=PASSIVE (threads block as soon as they are idle) unless the environment
  already says otherwise; OpenMP reads it once, as torch loads it, so `cluster/__init__.py`
  calls it before anything imports torch.
* **Fewer threads when the machine is busy.** `run.torch_threads=0` ("auto") runs torch on
  the CPUs this process may use less those other processes keep busy, at least one,
  measured when training starts and again every `RECHECK_S` seconds (`ThreadGovernor`).
  Another thread count can change float summation order, so a run that must repeat
  bit for bit keeps a fixed count (the default, 1).
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

log = logging.getLogger(__name__)

RECHECK_S = 10.0  # seconds between measurements of an "auto" thread count


def prefer_sleeping_threads() -> None:
    """OpenMP threads block when idle instead of spinning (OMP_WAIT_POLICY=PASSIVE), unless
    OMP_WAIT_POLICY is already set; takes effect only before torch is first imported."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _runnable_here() -> int:
    """Threads of this process that are running or runnable now (/proc/self/task)."""
    count = 0
    for stat in Path("/proc/self/task").glob("*/stat"):
        try:
            state = stat.read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        count += state == "R"
    return count


def busy_elsewhere(samples: int = 10, gap_s: float = 0.01) -> float:
    """CPUs other processes keep busy now: the mean over `samples` readings of the tasks the
    kernel counts as runnable (/proc/loadavg) less this process's runnable threads. Where
    /proc is missing, the 1-minute load average (which counts this process too)."""
    readings = []
    for i in range(samples):
        try:
            running = int(Path("/proc/loadavg").read_text().split()[3].split("/")[0])
        except (OSError, IndexError, ValueError):
            return os.getloadavg()[0]
        readings.append(max(0, running - _runnable_here()))
        if i + 1 < samples:
            time.sleep(gap_s)
    return sum(readings) / len(readings)


def auto_threads(limit: int | None = None) -> int:
    """The CPUs left to this process: usable CPUs less those busy elsewhere, within
    [1, limit] (limit: the usable CPUs by default)."""
    usable = usable_cpus()
    free = usable - int(busy_elsewhere() + 0.5)
    return max(1, min(limit or usable, free))


class ThreadGovernor:
    """torch's intra-op thread count for a training process.

    Calling loop::

        governor = ThreadGovernor(cfg.run.torch_threads)   # sets the count at once
        while training:
            governor.tick()                                 # "auto": re-measured now and then

    Args:
        requested: threads (>= 1), or 0 for "auto" (`auto_threads`).
        every_s: seconds between measurements in "auto".
    """

    def __init__(self, requested: int, every_s: float = RECHECK_S):
        import torch

        self.torch, self.requested, self.every_s = torch, requested, every_s
        self.last = time.monotonic()
        self.used: list[int] = []  # every count set, in order
        self._set(requested or auto_threads())

    def _set(self, n: int) -> None:
        if not self.used or self.used[-1] != n:
            if self.used:
                log.info(
                    "torch threads %d -> %d (other processes keep CPUs busy)", self.used[-1], n
                )
            self.torch.set_num_threads(n)
            self.used.append(n)

    def tick(self) -> None:
        """With "auto", measure again once `every_s` seconds have passed since the last."""
        if self.requested or time.monotonic() - self.last < self.every_s:
            return
        self._set(auto_threads())
        self.last = time.monotonic()

"""How a credit process shares the CPU with the others on its machine.

Two settings, each made once per process:

* **Threads that sleep soon after they are idle.** torch's CPU wheel runs its intra-op
  threads on GNU OpenMP, whose default lets every thread spin for a while after each parallel
  region. On a machine where other processes want the cores, the spinning threads take CPU
  from them, and a thread descheduled in turn holds up every region that waits for it: beside
  one busy loop on the 2-core machine, 10k env steps of `credit bench learn` on two threads
  did not finish in 400 s against 8.4 s alone. Sleeping at once (OMP_WAIT_POLICY=PASSIVE)
  costs a wake-up per region instead, which made the quiet 3m benchmark 1.5-1.8x slower than
  a short spin first. `prefer_sleeping_threads` sets OMP_WAIT_POLICY=PASSIVE with
  GOMP_SPINCOUNT=10000 (`SHORT_SPIN`: libgomp spins that many times, under a millisecond,
  before a thread sleeps, whatever the policy), unless the environment sets
  OMP_WAIT_POLICY itself, which then decides both. OpenMP reads them once, as torch loads
  it, so `cluster/__init__.py` calls it before anything imports torch. With the short spin
  the auto thread count below slowed 1.9-2.2x beside one busy process per core; a fixed count
  of two threads slowed 3.3x there (PASSIVE alone: 1.8x), so `ThreadGovernor` warns when a
  fixed count above one starts on a busy machine (results/bench/NOTES.md, "A short spin").
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
SHORT_SPIN = "10000"  # GOMP_SPINCOUNT: spins before an idle OpenMP thread sleeps


def prefer_sleeping_threads() -> None:
    """OpenMP threads spin briefly when idle, then block (OMP_WAIT_POLICY=PASSIVE,
    GOMP_SPINCOUNT=SHORT_SPIN unless set), unless OMP_WAIT_POLICY is already set, in which
    case the environment decides both; takes effect only before torch is first imported."""
    if "OMP_WAIT_POLICY" not in os.environ:
        os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
        os.environ.setdefault("GOMP_SPINCOUNT", SHORT_SPIN)


def spinning() -> bool:
    """Whether this process's OpenMP threads spin before they sleep (as the environment set
    them before torch loaded: a policy other than PASSIVE, or a spin count above 0)."""
    if os.environ.get("OMP_WAIT_POLICY", "").upper() != "PASSIVE":
        return True  # libgomp's default and ACTIVE both spin
    count = os.environ.get("GOMP_SPINCOUNT", "0").strip().lower()
    if count in ("infinite", "infinity"):
        return True
    try:
        return int(count.rstrip("kmgt") or "0") > 0  # libgomp takes 10k, 2M, ...
    except ValueError:  # libgomp ignores a value it cannot read: PASSIVE's 0 stays
        return False


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
        if requested > 1 and spinning():
            busy = busy_elsewhere()
            if busy >= 0.5:
                log.warning(
                    "torch threads fixed at %d while other processes keep about %.1f CPUs busy:"
                    " threads that spin before they sleep (OMP_WAIT_POLICY=%s, GOMP_SPINCOUNT=%s)"
                    " slow such a run far more than run.torch_threads=0 (auto) would",
                    requested,
                    busy,
                    os.environ.get("OMP_WAIT_POLICY", "unset"),
                    os.environ.get("GOMP_SPINCOUNT", "unset"),
                )

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

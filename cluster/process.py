"""The process-wide settings of a training process, made once at its entry point.

`configure(run)` is called by every entry that trains (`credit train` in either mode, the
reproductions' pair workers, the benchmarks and inspections that train, the demo's report)
before it builds a trainer; no constructor touches process-global state. It sets:

* torch's intra-op thread count, `run.torch_threads` (0: "auto", re-measured by `tick`,
  which the loop calls once per iteration; `cluster.cpu.ThreadGovernor`);
* glibc's allocator to keep freed memory, with `run.keep_freed_memory` (`cluster.alloc`);
* torch's global random seed, `run.seed` (the networks' initial weights draw from it).

OpenMP's wait policy is the one setting made earlier: it must be in the environment before
torch loads, so importing the package `cluster` sets it (`cluster.cpu.prefer_sleeping_threads`).
"""

from __future__ import annotations

import torch

from cluster.alloc import keep_freed_memory
from cluster.config.train import RunConfig
from cluster.cpu import ThreadGovernor

_governor: ThreadGovernor | None = None  # the training run's thread count, once configured


def configure(run: RunConfig) -> None:
    """Make the process-wide settings of a training run (see the module docstring)."""
    global _governor
    _governor = ThreadGovernor(run.torch_threads)
    if run.keep_freed_memory:
        keep_freed_memory()
    torch.manual_seed(run.seed)


def tick() -> None:
    """With run.torch_threads "auto", measure the free CPUs again now and then."""
    if _governor is not None:
        _governor.tick()


def threads_used() -> list[int]:
    """Every torch thread count the configured run has set, in order."""
    return list(_governor.used) if _governor is not None else []

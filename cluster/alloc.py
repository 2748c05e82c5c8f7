"""Keep freed heap memory in the process (glibc's allocator).

By default glibc serves every allocation above its mmap threshold (at most 32 MiB) with a
fresh `mmap` and unmaps it again on free, so a learner whose update allocates tensors of tens
of MiB (bane_vs_bane: the agents' GRU inputs of a batch are ~50 MiB) pays the kernel for
mapping and zeroing those pages on every update, and again after the heap is trimmed.
`keep_freed_memory` turns both off: big blocks come from the heap and freed memory stays
there for the next update. The process's resident memory then stays at its peak.
`credit bench update --env skirmish/bane_vs_bane --algos vdn,rdn` measured VDN 402 -> 334 ms
and RDN 601 -> 465 ms per update with it; on 3m (small tensors) nothing changes.

What it costs in memory (issue 35; RDN, bane_vs_bane, 3 seeds, local mode, glibc's
mallinfo2 after every round, load 6-12 on the 2-core machine):

* The heap grows to the update's working set (the peak of one update: ~2.2 GiB for 3 seeds,
  batches of 32 padded to ~90-150 steps) on top of what was freed before the first update
  (the greedy evaluation at t_env 0 and the rollouts: ~0.57 GiB), and stays there: after 8
  updates 2.85 GiB of heap, of which 0.45 GiB in use between updates. Without it the
  same run's peak was 2.73 GiB against 3.34 GiB (0.6 GiB, a fixed cost that does not grow
  with the run), and updates were 1.6-2.3x slower under that load (one recorded 3-seed
  batch, 6 updates per process, two rounds interleaved: medians 3.4 and 3.9 s with it,
  5.5 and 9.0 s without).
* What made the resident size grow by about twice the stored bytes was the replay on that
  heap: the old dense episodes (37.8 KB per env step) were malloc'd between the updates'
  blocks, so each freed block was pinned behind newer episodes and the next update needed
  fresh memory on top. Measured at 828260c: heap 3.04 -> 3.40 GiB from update 8 to 16 while
  the replay grew by 51 MiB. Stored episodes now live packed (`buffer_service.packed`, a
  twelfth of the bytes) in buffers of their own outside the heap (`stored_buffer`: an
  anonymous mapping each, unmapped with the episode), and the same steps gave heap 2.85 ->
  2.87 GiB. Resident memory is then the heap's peak plus the replay's byte budget.
* Large batches and updates: a padded batch of a big map now lives in mappings of its own
  (`buffer_service.episode.batch_zeros`), and an update runs in passes of bounded size
  (`learner.passes`), so the heap's peak is one pass's working set rather than a whole
  batch's; the judged 3-seed bane_vs_bane RDN run peaked at 1.28 GiB against 4.24 GiB at
  828260c (results/bench/NOTES.md, "Updates in passes").
"""

from __future__ import annotations

import ctypes
import logging
import sys

log = logging.getLogger(__name__)

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
M_MMAP_MAX = -4
_INT_MAX = 2**31 - 1


def keep_freed_memory() -> bool:
    """Tell glibc's malloc to serve large blocks from the heap and never trim it. Returns
    whether the allocator accepted both settings (False off glibc; nothing changes then)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    ok = mallopt(M_MMAP_MAX, 0) == 1 and mallopt(M_TRIM_THRESHOLD, _INT_MAX) == 1
    if not ok:
        log.warning("glibc's mallopt refused M_MMAP_MAX=0 / M_TRIM_THRESHOLD; left as it was")
    return ok

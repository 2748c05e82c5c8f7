"""`cluster.alloc.keep_freed_memory`: freed memory stays in the process (glibc)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

# Allocate and free 256 MiB (one block, as a big tensor would be), then report how much of it
# is still resident.
PROBE = textwrap.dedent(
    """
    import sys, torch
    from cluster.alloc import keep_freed_memory
    def rss_mib():
        for line in open("/proc/self/status"):
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    kept = keep_freed_memory() if sys.argv[1] == "keep" else None
    base = rss_mib()
    block = torch.ones(64 * 2**20)  # 256 MiB, touched
    del block
    print(kept, round(rss_mib() - base))
    """
)


def _probe(mode: str) -> tuple[str, int]:
    out = subprocess.run(
        [sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True
    ).stdout.split()
    return out[0], int(out[1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt is Linux-only")
def test_freed_memory_stays_resident_only_when_asked():
    kept, after_keep = _probe("keep")
    default, after_default = _probe("default")
    if kept != "True":
        pytest.skip("this libc refused mallopt (not glibc)")
    assert default == "None"
    assert after_default < 64, "glibc returns a freed 256 MiB block to the OS by default"
    assert after_keep > 200, "with keep_freed_memory the freed block stays in the heap"

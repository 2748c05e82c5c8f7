"""What every benchmark's JSON carries: the machine and the command that made it."""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from typing import Any


def machine() -> dict[str, Any]:
    import numpy as np

    info: dict[str, Any] = {
        "hostname": platform.node(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "numpy": np.__version__,
    }
    try:
        import torch

        info["torch"] = torch.__version__
        info["torch_threads"] = torch.get_num_threads()
    except ImportError:
        pass
    return info


def emit(name: str, figures: dict[str, Any], out: str | None = None) -> dict[str, Any]:
    """Print (and optionally write) one JSON object for benchmark `name`."""
    record = {
        "benchmark": name,
        "command": " ".join(["credit", *sys.argv[1:]]) if sys.argv else "",
        "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": machine(),
        **figures,
    }
    text = json.dumps(record, indent=2)
    print(text)
    if out:
        with open(out, "w") as f:
            f.write(text + "\n")
    return record

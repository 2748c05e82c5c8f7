"""Where a training run logs its evaluations and learner losses (`run.loggers`).

jsonl        OUT/metrics.jsonl, one JSON object per evaluation (always on: resume, the
             reports and `credit demo` read it).
tensorboard  OUT/tensorboard/events.out.tfevents.*: the same scalars as metrics.jsonl at
             step t_env, and each learner loss and diagnostic as learner/<key> (its mean
             over the updates since the previous evaluation). Needs `tensorboard`
             (pip install 'credit[tensorboard]').
wandb        a Weights & Biases run (project $WANDB_PROJECT, default "credit"; files under
             OUT/wandb; WANDB_MODE=offline logs without an account) with the same
             scalars and the resolved config. Needs `wandb` (pip install 'credit[wandb]').
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from cluster.errors import UsageError

_PACKAGES = {"tensorboard": "tensorboard", "wandb": "wandb"}


def check_installed(names: tuple[str, ...] | list[str]) -> None:
    """UsageError naming the extra to install when a logger's package is missing."""
    import importlib.util

    for name in names:
        package = _PACKAGES.get(name)
        if package and importlib.util.find_spec(package) is None:
            raise UsageError(
                f"run.loggers has {name}, but the {package} package is not installed: "
                f"pip install 'credit[{name}]'"
            )


def scalars(records: list, learner: dict[str, float]) -> dict[str, float]:
    """One evaluation's scalars by tag: metrics.jsonl's fields (prefixed member<i>/ when a
    run trains several seeds) and learner/<key>."""
    out: dict[str, float] = {}
    for r in records:
        prefix = f"member{r.member}/" if len(records) > 1 else ""
        for k, v in r.as_json().items():
            if k != "t_env" and isinstance(v, int | float):
                out[prefix + k] = float(v)
    out.update({f"learner/{k}": float(v) for k, v in learner.items()})
    return out


class RunLoggers:
    """The loggers `names` of one run in folder `out` (module docstring); `log` each
    evaluation, `close` at the end."""

    def __init__(self, names: tuple[str, ...], out: Path, config: dict[str, Any], append: bool):
        check_installed(names)
        self.jsonl = open(out / "metrics.jsonl", "a" if append else "w")  # noqa: SIM115
        self.tb = self.wandb = None
        if "tensorboard" in names:
            from torch.utils.tensorboard import SummaryWriter

            self.tb = SummaryWriter(log_dir=str(out / "tensorboard"))
        if "wandb" in names:
            import wandb

            project = os.environ.get("WANDB_PROJECT", "credit")
            self.wandb = wandb.init(project=project, dir=str(out), config=config, name=out.name)

    def log(self, records: list, learner: dict[str, float]) -> None:
        for r in records:
            self.jsonl.write(json.dumps(r.as_json()) + "\n")
        self.jsonl.flush()
        if self.tb is None and self.wandb is None:
            return
        step = records[0].t_env
        values = scalars(records, learner)
        if self.tb is not None:
            for tag, v in values.items():
                self.tb.add_scalar(tag, v, global_step=step)
            self.tb.flush()
        if self.wandb is not None:
            self.wandb.log(values, step=step)

    def close(self) -> None:
        self.jsonl.close()
        if self.tb is not None:
            self.tb.close()
        if self.wandb is not None:
            self.wandb.finish()

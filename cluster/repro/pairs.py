"""One (algorithm, env) pair of a `credit repro` experiment and how it reports: `Pair`, the
run options (`FanOutConfig`), the events a pair's process sends (`PairEvent`, `Reporter`,
`run_pair`) and the driver's `Collector`, which writes each evaluation line to
OUT/evals/<key>.jsonl (`Pair.key`: <env>__<algo>, then .g<G> for seed group G) as it
arrives and logs each pair's start, restarts and end. Shared by the local pool
(`cluster.repro.fanout`) and the Ray tasks (`cluster.repro.fanout_ray`)."""

from __future__ import annotations

import json
import logging
import os
import socket
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

log = logging.getLogger(__name__)

POLL_S = 1.0  # how often the driver collects events while pairs run


@dataclass(frozen=True)
class Pair:
    """One (algorithm, env) run of an experiment (all its seeds batched in one trainer);
    `group`: its seed group (`cluster.repro.groups`; 0 unless --seed-group says)."""

    algo: str
    env: str
    group: int = 0

    @property
    def key(self) -> str:
        """File stem of the pair's evaluation log, checkpoint folder and record:
        `<env with - for />__<algo>` (a map file's absolute path without its leading /), then
        `.g<group>` for a seed group other than 0."""
        stem = f"{self.env.lstrip('/').replace('/', '-')}__{self.algo}"
        return stem + (f".g{self.group}" if self.group else "")

    @property
    def label(self) -> str:
        return f"{self.algo}@{self.env}" + (f" (seed group {self.group})" if self.group else "")


@dataclass(frozen=True)
class FanOutConfig:
    """Where the pairs run.

    Args:
        workers: local mode: processes running pairs in parallel (1 = in this process).
        address: None = local mode; "auto" = the cluster `credit cluster up` recorded (else
            Ray's own discovery); "host:port" = that Ray head.
        cpus_per_pair: Ray mode: CPUs each pair's task asks for (its torch threads are
            `run.torch_threads`, 1 by default; ask for as many CPUs as it uses).
        max_retries: Ray mode: times a pair is restarted after its worker process or node dies.
        ship_code: Ray mode: upload this driver's packages to every node
            (`cluster.repro.fanout_ray`).
    """

    workers: int = 2
    address: str | None = None
    cpus_per_pair: float = 1.0
    max_retries: int = 3
    ship_code: bool = True

    def validate(self) -> None:
        """Raise ValueError for a setting no run could use."""
        if self.workers < 1:
            raise ValueError(f"--workers must be >= 1, got {self.workers}")
        if self.cpus_per_pair <= 0:
            raise ValueError(f"--cpus-per-pair must be > 0, got {self.cpus_per_pair}")
        if self.max_retries < 0:
            raise ValueError(f"--max-retries must be >= 0, got {self.max_retries}")


@dataclass(frozen=True)
class PairEvent:
    """What a pair's process tells the driver while it runs.

    Args:
        pair: the pair.
        kind: "started" (a new attempt at the pair), "resumed" (the attempt continues from
            a checkpoint), "evaluated", "checkpointed" or "finished" (the last event of an
            attempt that returned its result).
        attempt: "<host>:<pid>:<start time ns>" of the attempt, so that lines of an attempt
            that died are told from the retry's.
        text: "evaluated": one JSON line of the pair's evaluation log; "resumed": JSON
            {t_env, lines: the log's lines up to the checkpoint}; "checkpointed": JSON
            {t_env, bytes, folder}.
        wall_s: "finished": seconds the attempt took.
    """

    pair: Pair
    kind: str
    attempt: str
    text: str = ""
    wall_s: float = 0.0


class EventSink(Protocol):
    """Where a pair's process puts its events: `sink.put(event)`, in order."""

    def put(self, event: PairEvent) -> None: ...


class Reporter:
    """The pair function's side: `report(line)` per evaluation after `start()`."""

    def __init__(self, sink: EventSink, pair: Pair):
        self.sink, self.pair = sink, pair
        self.attempt = f"{socket.gethostname()}:{os.getpid()}:{time.time_ns()}"

    def start(self) -> None:
        self.sink.put(PairEvent(self.pair, "started", self.attempt))

    def __call__(self, line: str) -> None:
        self.sink.put(PairEvent(self.pair, "evaluated", self.attempt, line))

    def resumed(self, t_env: int, lines: list[str]) -> None:
        """The attempt continues from a checkpoint at `t_env` whose log is `lines`."""
        text = json.dumps({"t_env": t_env, "lines": lines})
        self.sink.put(PairEvent(self.pair, "resumed", self.attempt, text))

    def checkpointed(self, info: dict) -> None:
        self.sink.put(PairEvent(self.pair, "checkpointed", self.attempt, json.dumps(info)))


PairFn = Callable[..., Any]  # fn(algo, env, *args, report=Callable[[str], None]) -> result


def run_pair(fn: PairFn, pair: Pair, args: tuple, sink: EventSink) -> Any:
    """Run one pair in this process, reporting to `sink`; returns fn's result."""
    report = Reporter(sink, pair)
    report.start()
    started = time.monotonic()
    result = fn(pair.algo, pair.env, *args, report=report)
    wall = time.monotonic() - started
    sink.put(PairEvent(pair, "finished", report.attempt, wall_s=wall))
    return result


@dataclass(frozen=True)
class StatusLine:
    """The driver's status line over every pair (`cluster.progress.Progress`).

    Args:
        total_steps: env steps of all pairs together (the bar's 100%).
        key: field of the evaluation lines shown per pair, its median over seeds ("won").
        name: what the line calls it ("win").
    """

    total_steps: int
    key: str = "won"
    name: str = "win"


class Collector:
    """The driver's side: writes each pair's evaluation log, logs its start and finish, and
    keeps the status line (env steps done: each pair's latest evaluation)."""

    def __init__(
        self, pairs: Sequence[Pair], log_dir: Path | None, status: StatusLine | None = None
    ):
        self.log_dir, self.total, self.status = log_dir, len(pairs), status
        self.attempt: dict[Pair, str] = {}
        self.starts: dict[Pair, int] = {}
        self.finished: set[Pair] = set()
        self.latest: dict[Pair, dict] = {}  # each pair's latest evaluation line
        self.bar = None
        if status is not None:
            from cluster.progress import Progress

            self.bar = Progress(status.total_steps)

    def _say(self, msg: str, *args: Any) -> None:
        if self.bar is not None and self.bar.tty:
            sys.stderr.write("\r\x1b[K")  # the log line replaces the bar; the next update redraws
        log.info(msg, *args)

    def tick(self) -> None:
        """Redraw the status line; the loops call it once per collection of events, so that
        its rate is measured over a collection period, not between events of one batch."""
        if self.bar is None:
            return
        key = self.status.key
        shown = []
        for pair, row in self.latest.items():
            values = sorted(row.get(key) or [0.0])
            shown.append(f"{pair.label} {values[len(values) // 2]:.2f}")
        steps = sum(int(row.get("t_env", 0)) for row in self.latest.values())
        pairs = f"{len(self.finished)}/{self.total} pairs done"
        latest = f"; {self.status.name} " + ", ".join(shown) if shown else ""
        self.bar.update(steps, pairs + latest)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()

    def _resumed(self, pair: Pair, resumed: dict) -> None:
        """The log becomes the checkpoint's: lines past it were made by the lost attempt."""
        lines = resumed["lines"]
        if self.log_dir is not None:
            (self.log_dir / f"{pair.key}.jsonl").write_text("".join(x + "\n" for x in lines))
        if lines:
            self.latest[pair] = json.loads(lines[-1])
        self._say(
            "pair %s resumed from its checkpoint at t_env %d (%d evaluations kept)",
            pair.label,
            resumed["t_env"],
            len(lines),
        )

    def skip(self, pair: Pair) -> None:
        """A pair that finished in an earlier run: counted as done, its log left as it is."""
        self.finished.add(pair)
        path = None if self.log_dir is None else self.log_dir / f"{pair.key}.jsonl"
        if path is not None and path.exists() and path.read_text().strip():
            self.latest[pair] = json.loads(path.read_text().splitlines()[-1])
        self._say("pair %s finished in an earlier run; not run again", pair.label)

    def handle(self, event: PairEvent) -> None:
        pair = event.pair
        if event.kind == "started":
            self.attempt[pair] = event.attempt
            self.starts[pair] = self.starts.get(pair, 0) + 1
            if self.log_dir is not None:  # a retry starts its log afresh
                (self.log_dir / f"{pair.key}.jsonl").write_text("")
            self.latest.pop(pair, None)
            host, pid, _ = event.attempt.rsplit(":", 2)
            again = self.starts[pair] > 1
            self._say(
                "pair %s %s on %s (pid %s)%s",
                pair.label,
                "restarted" if again else "started",
                host,
                pid,
                f", attempt {self.starts[pair]}: the previous one was lost" if again else "",
            )
        elif event.attempt != self.attempt.get(pair):
            return  # a lost attempt's late event
        elif event.kind == "evaluated":
            if self.log_dir is not None:
                with open(self.log_dir / f"{pair.key}.jsonl", "a") as f:
                    f.write(event.text.rstrip("\n") + "\n")
            if self.bar is not None:
                self.latest[pair] = json.loads(event.text)
        elif event.kind == "resumed":
            self._resumed(pair, json.loads(event.text))
        elif event.kind == "checkpointed":
            info = json.loads(event.text)
            self._say(
                "pair %s checkpoint at t_env %d: %.1f MB in %s (up to twice that while the "
                "next is written)",
                pair.label,
                info["t_env"],
                info["bytes"] / 1e6,
                info["folder"],
            )
        elif event.kind == "finished":
            self.finished.add(pair)
            self._say(
                "pair %s finished in %.0f s (%d/%d pairs done)",
                pair.label,
                event.wall_s,
                len(self.finished),
                self.total,
            )

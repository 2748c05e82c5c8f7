"""`credit repro` runs that survive interruption: pair checkpoints and finished-pair records.

Every (algorithm, env) pair checkpoints into OUT/resume/<env>__<algo>/ every
`--checkpoint-every` env steps (`PairJournal`, in the pair's own process): the seed-batched
trainer's whole state (networks, target networks, optimisers, the replay tables, every random
state: torch, numpy, python, the workers' action sampling, the envs', the replay's sampling;
counters) and the pair's evaluation log so far, with the commit each part was trained at. A
pair keeps one checkpoint: the next is written beside it and replaces it, so while it is
written the pair uses up to twice the disk of one; each checkpoint's size is logged. The
finished pair removes its checkpoint and the driver records it in OUT/pairs/<key>.json
(`PairStore`). A pair's seed group G > 0 (`cluster.repro.groups`) has its own of each:
OUT/resume/<env>__<algo>.g<G>/ and OUT/pairs/<env>__<algo>.g<G>.json (`Pair.key`).

Running the same command again skips the finished pairs (their curves come from the records)
and continues every other pair from its checkpoint: with one worker and a fixed seed the
evaluation log is the one an uninterrupted run writes (but for wall times), and a pair killed
at any moment loses fewer than `--checkpoint-every` env steps of training. A record or a
checkpoint made with other settings (seeds, --t-max, --test-interval, --set) is refused with a
UsageError rather than mixed in.

With `--address`, a pair writes its checkpoints on the node that runs it, at the driver's
OUT/resume path: a retried or rerun pair continues from them where it can read that path (one
machine, or a filesystem the nodes share), and starts again from zero elsewhere.
"""

from __future__ import annotations

import contextlib
import ctypes
import fcntl
import json
import logging
import os
import shutil
import signal
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cluster.errors import UsageError
from cluster.repro.pairs import Pair

log = logging.getLogger(__name__)

CHECKPOINT_EVERY = 20_000  # default --checkpoint-every (env steps)
RESUME_FOLDER = "resume"  # OUT/resume/<key>/: each unfinished pair's checkpoint
DONE_FOLDER = "pairs"  # OUT/pairs/<key>.json: each finished pair's record
JOURNAL = "pair.json"  # in a checkpoint: the evaluation log, commits, wall time, settings
PR_SET_PDEATHSIG = 1  # prctl(2)


def code_commit() -> str:
    """The git commit of the code running (`<sha>`; `<sha>-dirty` when tracked files differ
    from it; "unknown" outside a git checkout)."""
    root = Path(__file__).resolve().parents[2]

    def git(*args: str) -> str:
        done = subprocess.run(
            ["git", "-C", str(root), *args], capture_output=True, text=True, timeout=30
        )
        if done.returncode != 0:
            raise OSError(done.stderr.strip())
        return done.stdout.strip()

    try:
        if Path(git("rev-parse", "--show-toplevel")).resolve() != root:
            return "unknown"  # an installed copy inside some other checkout
        sha = git("rev-parse", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return sha + ("-dirty" if dirty else "")


@dataclass(frozen=True)
class ResumeConfig:
    """What every pair of a repro run is told about checkpoints.

    Args:
        out: the run's output folder as an absolute path (None: no checkpoints, no records).
        every: env steps between a pair's checkpoints (0: none; finished pairs are still
            recorded and skipped).
        commit: the code's commit (`code_commit`, taken by the driver).
        settings: what the command sets for every pair (seeds, config overrides); a
            checkpoint or record made with other settings is refused.
    """

    out: str | None
    every: int = CHECKPOINT_EVERY
    commit: str = "unknown"
    settings: dict = field(default_factory=dict)

    def fingerprint(self, pair: Pair) -> dict:
        return {"algo": pair.algo, "env": pair.env, **self.settings}

    def pair_folder(self, pair: Pair) -> Path | None:
        """The pair's checkpoint folder, OUT/resume/<key> (None without checkpoints)."""
        if self.out is None or self.every <= 0:
            return None
        return Path(self.out) / RESUME_FOLDER / pair.key


def _checkpoint_journal(folder: Path) -> Path:
    """The journal of the checkpoint `TrainerCore.save` left in `folder` (or its .old copy)."""
    from cluster.checkpoint import checkpoint_folder

    return checkpoint_folder(folder) / JOURNAL


def _check_settings(saved: dict, wanted: dict, what: str, where: Path) -> None:
    if saved != wanted:
        changed = sorted(k for k in set(saved) | set(wanted) if saved.get(k) != wanted.get(k))
        detail = "; ".join(f"{k}: {saved.get(k)!r} there, {wanted.get(k)!r} now" for k in changed)
        raise UsageError(
            f"{where} holds {what} made with other settings ({detail}); rerun with the "
            "settings it was made with, or use another --out (or remove it)"
        )


def die_with_parent(parent: int) -> None:
    """Linux: this process is killed when its parent (pid `parent`) dies, kill -9 included,
    so that a pool worker of a killed driver does not go on training a pair that the rerun
    continues; it exits at once if that parent is already gone."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):  # not Linux: the worker ends when the pair does
        return
    if os.getppid() != parent:
        os._exit(1)


def _lock(folder: Path) -> Any:
    """Hold OUT/resume/<key>.lock for this process (released when it ends, however it ends);
    raises UsageError when another process trains the pair into `folder`."""
    folder.parent.mkdir(parents=True, exist_ok=True)
    f = open(folder.with_name(folder.name + ".lock"), "a+")  # noqa: SIM115 - held until finish
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        f.close()
        raise UsageError(
            f"another process is training into {folder} (its .lock is held): the same run "
            "twice at once? Stop the other one, or use another --out"
        ) from None
    return f


def folder_bytes(folder: Path) -> int:
    return sum(f.stat().st_size for f in Path(folder).rglob("*") if f.is_file())


class PairJournal:
    """A pair's evaluation log and checkpoints, in the process that trains it.

    Calling loop::

        with PairJournal(resume, Pair(algo, env), report) as journal:
            cfg = load_train_config(algo, env, [], overrides + journal.overrides())
            configure(cfg.run)
            trainer = LocalTrainer(cfg, n_ensemble=seeds)
            journal.attach(trainer)          # continues from the checkpoint, if any
            trainer.train(on_eval=lambda records: journal.add(row_of(records)))
            journal.finish()                 # removes the checkpoint
        journal.rows, journal.commits, journal.wall_s

    Leaving the `with` block, however it is left, lets go of the pair's lock (a second
    process training the same pair into the same folder is refused while it is held).

    Args:
        resume: the run's checkpoint settings (None: no checkpoints).
        pair: the pair.
        report: the pair's Reporter (`cluster.repro.pairs`): one JSON line per evaluation,
            and its `resumed` / `checkpointed` events when it has them; None for none.
    """

    def __init__(self, resume: ResumeConfig | None, pair: Pair, report: Any = None):
        self.resume = resume or ResumeConfig(None)
        self.pair, self.report = pair, report
        self.folder = self.resume.pair_folder(pair)
        self.rows: list[dict] = []
        self.commits = [self.resume.commit]
        self.wall_offset = 0.0
        self.started = time.monotonic()
        self.trainer: Any = None
        self.lock: Any = None

    def __enter__(self) -> PairJournal:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.lock is not None:
            self.lock.close()
            self.lock = None

    @property
    def wall_s(self) -> float:
        return self.wall_offset + time.monotonic() - self.started

    def overrides(self) -> list[str]:
        """Config overrides the pair needs (its checkpoint interval)."""
        return [f"run.save_interval={self.resume.every}"] if self.folder else []

    def attach(self, trainer: Any) -> None:
        """Checkpoint `trainer` (a LocalTrainer) into the pair's folder from now on, first
        restoring the checkpoint there when there is one."""
        self.trainer, self.started = trainer, time.monotonic()
        if self.folder is None:
            return
        self.lock = _lock(self.folder)
        trainer.core.checkpointer.folder = self.folder
        trainer.loop.checkpoint_files.append(self._write)
        journal = _checkpoint_journal(self.folder)
        if not journal.exists():
            return
        saved = json.loads(journal.read_text())
        _check_settings(
            saved["settings"], self.resume.fingerprint(self.pair), "a checkpoint", journal.parent
        )
        trainer.restore(self.folder)
        self.rows, self.commits = saved["rows"], saved["commits"]
        if self.resume.commit not in self.commits:
            self.commits.append(self.resume.commit)
        self.wall_offset = saved["wall_s"]
        t_env = trainer.core.t_env
        if hasattr(self.report, "resumed"):  # the driver logs it
            self.report.resumed(t_env, [json.dumps(r) for r in self.rows])
        else:
            log.info("pair %s resumed from %s at t_env %d", self.pair.label, journal.parent, t_env)

    def add(self, row: dict) -> dict:
        """One evaluation's row: its wall time and commit added, logged and reported."""
        row = {**row, "wall_s": round(self.wall_s, 1), "commit": self.resume.commit}
        self.rows.append(row)
        if self.report is not None:
            self.report(json.dumps(row))
        return row

    def _write(self, folder: Path) -> None:
        """Add the journal to a checkpoint being written (a TrainLoop checkpoint file)."""
        journal = {
            "settings": self.resume.fingerprint(self.pair),
            "t_env": self.trainer.core.t_env,
            "rows": self.rows,
            "commits": self.commits,
            "wall_s": self.wall_s,
        }
        (folder / JOURNAL).write_text(json.dumps(journal) + "\n")
        info = {
            "t_env": journal["t_env"],
            "bytes": folder_bytes(folder),
            "folder": str(self.folder),
        }
        if hasattr(self.report, "checkpointed"):  # the driver logs it
            self.report.checkpointed(info)
        else:
            log.info(
                "pair %s checkpoint at t_env %d: %.1f MB in %s",
                self.pair.label,
                info["t_env"],
                info["bytes"] / 1e6,
                self.folder,
            )

    def finish(self) -> None:
        """The pair is trained: stop checkpointing and remove its checkpoint."""
        if self.folder is None or self.trainer is None:
            return
        self.trainer.loop.checkpoint_files.remove(self._write)
        self.trainer.core.checkpointer.folder = None
        for suffix in ("", ".old", ".tmp"):
            shutil.rmtree(self.folder.with_name(self.folder.name + suffix), ignore_errors=True)
        Path(self.lock.name).unlink(missing_ok=True)
        self.__exit__()
        with contextlib.suppress(OSError):  # OUT/resume, once no pair has a checkpoint left
            self.folder.parent.rmdir()


class PairStore:
    """The driver's record of finished pairs, OUT/pairs/<key>.json: the settings they were
    made with and their result (`encode`d as JSON; `decode` turns it back).

    Args:
        resume: the run's checkpoint settings (its output folder, the fingerprints).
        encode: a pair's result -> JSON-able dict.
        decode: the inverse.
    """

    def __init__(
        self, resume: ResumeConfig, encode: Callable[[Any], dict], decode: Callable[[dict], Any]
    ):
        if resume.out is None:
            raise ValueError("a PairStore needs the run's output folder (ResumeConfig.out)")
        self.folder = Path(resume.out) / DONE_FOLDER
        self.resume, self.encode, self.decode = resume, encode, decode

    def path(self, pair: Pair) -> Path:
        return self.folder / f"{pair.key}.json"

    def finished(self, pair: Pair) -> Any | None:
        """The pair's recorded result, or None when it has not finished. Raises UsageError
        when its record, or its checkpoint, was made with other settings."""
        wanted = self.resume.fingerprint(pair)
        ckpt = self.resume.pair_folder(pair)
        if ckpt is not None and _checkpoint_journal(ckpt).exists():
            saved = json.loads(_checkpoint_journal(ckpt).read_text())
            _check_settings(saved["settings"], wanted, "a checkpoint", ckpt)
        path = self.path(pair)
        if not path.exists():
            return None
        record = json.loads(path.read_text())
        _check_settings(record["settings"], wanted, "a finished pair", path)
        return self.decode(record["result"])

    def record(self, pair: Pair, result: Any) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        record = {"settings": self.resume.fingerprint(pair), "result": self.encode(result)}
        tmp = self.path(pair).with_suffix(".tmp")
        tmp.write_text(json.dumps(record) + "\n")
        tmp.replace(self.path(pair))

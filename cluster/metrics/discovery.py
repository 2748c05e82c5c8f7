"""Prometheus file service discovery: each run's OUT/targets.json, the per-machine folder of live
runs' links that `credit metrics up` and `credit dashboard` read, and parsing of targets."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import tempfile
from collections.abc import Iterable, Mapping
from pathlib import Path

log = logging.getLogger(__name__)

_LABEL_NAME = re.compile(r"^[a-zA-Z_][a-zA-Z0-9_]*$")


def default_state_dir() -> Path:
    """Where `credit` keeps run-time state: $CREDIT_STATE_DIR, else ~/.credit."""
    return Path(os.environ.get("CREDIT_STATE_DIR") or Path.home() / ".credit")


def runs_sd_dir() -> Path:
    """Where every live cluster run on this machine links its own file-SD file (one
    `<run folder name>-<hash>.json` link per run, pointing at the run's OUT/targets.json);
    `credit metrics up` and `credit dashboard` read every file in it."""
    return default_state_dir() / "metrics" / "runs"


def runs_sd_glob() -> str:
    """The file_sd glob over `runs_sd_dir()` that Prometheus is given."""
    return str(runs_sd_dir() / "*.json")


def register_run_sd(targets_file: str | Path) -> Path:
    """Link a run's own file-SD file into `runs_sd_dir()`, so that whatever scrapes "every
    live run" finds it; prunes the links of runs that are gone first. The same file always
    gets the same link (replaced atomically).

    Returns:
        The link.
    """
    target = Path(targets_file).resolve()
    prune_run_sd()
    digest = hashlib.sha1(str(target).encode()).hexdigest()[:12]
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", target.parent.name) or "run"
    link = runs_sd_dir() / f"{name}-{digest}.json"
    link.parent.mkdir(parents=True, exist_ok=True)
    tmp = link.with_name(f".{link.name}.tmp")  # not matched by the *.json glob
    tmp.unlink(missing_ok=True)
    tmp.symlink_to(target)
    os.replace(tmp, link)
    return link


def unregister_run_sd(link: str | Path) -> None:
    """Remove a run's link (the run has ended); its own targets file stays."""
    Path(link).unlink(missing_ok=True)


def _run_alive(targets_file: Path) -> bool:
    """Whether the run that wrote `targets_file` still runs: its folder's cluster.json names
    a learner pid that is alive (a run without cluster.json yet counts as alive)."""
    if not targets_file.exists():
        return False
    try:
        pid = int(json.loads((targets_file.parent / "cluster.json").read_text())["learner"]["pid"])
    except FileNotFoundError:
        return True
    except (ValueError, KeyError, TypeError):
        return False
    return pid_alive(pid)


def pid_alive(pid: int) -> bool:
    """Whether process `pid` exists and is not a zombie (an exited child never reaped)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except (OSError, IndexError):
        return True


def prune_run_sd() -> list[Path]:
    """Remove the links of runs that are gone (killed, or their folder deleted); returns them."""
    folder = runs_sd_dir()
    removed = []
    for link in sorted(folder.glob("*.json")) if folder.is_dir() else []:
        if not _run_alive(link.resolve()):
            link.unlink(missing_ok=True)
            removed.append(link)
            log.info("dropped the file-SD link of a run that is gone: %s", link)
    return removed


def read_runs_sd() -> list[tuple[str, int]]:
    """Every (host, port) of every live run's file-SD file (a run's broken file is skipped
    with a warning, so one bad run does not hide the others)."""
    folder = runs_sd_dir()
    out: list[tuple[str, int]] = []
    for link in sorted(folder.glob("*.json")) if folder.is_dir() else []:
        try:
            out += read_file_sd(link)
        except ValueError as e:
            log.warning("skipping %s: %s", link, e)
    return out


def write_file_sd(
    path: str | Path,
    targets: Iterable[tuple[str, int]],
    labels: Mapping[str, str] | None = None,
) -> Path:
    """Write a Prometheus file_sd JSON file listing `targets`, atomically.

    Prometheus re-reads the file when it changes; a reader never sees a half-written file
    because the content goes to a temporary file in the same folder that then replaces `path`.

    Args:
        path: the file to (re)write; parent folders are created.
        targets: (host, port) of every exporter.
        labels: labels Prometheus attaches to every target (e.g. {"job": "credit"}).

    Returns:
        The path written.
    """
    labels = dict(labels or {})
    for key, value in labels.items():
        if not _LABEL_NAME.match(key) or key.startswith("__"):
            raise ValueError(f"invalid Prometheus label name {key!r}")
        if not isinstance(value, str):
            raise ValueError(f"label {key!r} must be a string, got {value!r}")
    entries = []
    for host, port in targets:
        if not host or not 0 < int(port) <= 65535:
            raise ValueError(f"bad target {host!r}:{port!r}")
        entries.append(f"{host}:{int(port)}")
    groups = [{"targets": entries, "labels": labels}] if entries else []
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(groups, f, indent=2)
            f.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def read_file_sd(path: str | Path) -> list[tuple[str, int]]:
    """Every (host, port) listed in a file_sd JSON file; [] when the file does not exist.

    Raises:
        ValueError: the file is not file_sd JSON (the message names the file).
    """
    path = Path(path)
    try:
        groups = json.loads(path.read_text())
    except FileNotFoundError:
        return []
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not JSON ({e})") from None
    if not isinstance(groups, list):
        raise ValueError(f"{path}: file_sd must be a JSON list of target groups")
    out: list[tuple[str, int]] = []
    for group in groups:
        for target in group.get("targets", []) if isinstance(group, dict) else []:
            out.append(parse_target(target))
    return out


def parse_target(text: str) -> tuple[str, int]:
    """`"127.0.0.1:9100"` -> ("127.0.0.1", 9100); ValueError naming the text otherwise."""
    host, sep, port = str(text).strip().rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) <= 65535:
        raise ValueError(f"target must be host:port, got {text!r}")
    return host, int(port)

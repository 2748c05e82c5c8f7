"""Seed groups: one (algorithm, env) pair's seeds split over several runs (`--seed-group G`).

A pair trains all its seeds batched in one trainer seeded from `run.seed`. A long pair can be
split: `--seeds 1` as group 0 in one session, `--seeds 2 --seed-group 1` in the next (or at
once, from a second command into the same --out), and the summariser treats them as one pair
of 3 seeds. Group G is a trainer of its own with its own files: OUT/evals/<key>.jsonl,
OUT/resume/<key>/ and OUT/pairs/<key>.json, where the key is `<env>__<algo>` for group 0 (the
files of every run made before groups existed) and `<env>__<algo>.g<G>` for G > 0.

Random streams. A trainer with run.seed = S and E members (cluster/process.py,
cluster/evaluation.py, cluster/launch/local.py) seeds torch's global generator (the
networks) with S, the acting worker's generator with S and the evaluation worker's with
S + 1; training env k (k < E * run.num_envs) with S + k and evaluation env k
(k < E * run.test_episodes) with S + 10_000 + k; member m's replay table with S * 1000 + m.
Group G trains with S = base + G * STRIDE (base: run.seed as configured, 0 unless
`--set run.seed`), and a group is refused unless every seed it uses lies in its own window
([G * STRIDE, (G + 1) * STRIDE), times 1000 for the tables): so no two groups of one base
ever share a seed, whatever their numbers of members.

Merging (`merge`): the groups' seeds are concatenated in group order at every evaluation all
groups have, matched by their index (evaluation k of every group is its k-th, at about k
test intervals; the exact t_env differs between groups as episode lengths do), up to the
shortest group (logged). The merged evaluation's t_env and wall time are the largest of the
groups' (every group had trained that long); learner diagnostics are seed-weighted means.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cluster.errors import UsageError
from cluster.repro.pairs import Pair

log = logging.getLogger(__name__)

STRIDE = 100_000  # run.seed of group G: base + G * STRIDE
MAX_GROUP = 999
TEST_ENV_OFFSET = 10_000  # cluster/evaluation.py: evaluation env k is seeded run.seed + 10_000 + k
TABLE_FACTOR = 1000  # cluster/launch/local.py: member m's table is seeded run.seed * 1000 + m
PER_SEED = ("won", "returns")  # evaluation-log keys holding one value per seed


def group_seed(group: int, base: int = 0) -> int:
    """run.seed of seed group `group` (base: run.seed as configured)."""
    return base + group * STRIDE


def streams(seed: int, members: int, num_envs: int, test_episodes: int) -> dict[str, range]:
    """The seeds a trainer with run.seed = `seed` and `members` members hands out, by kind."""
    test = seed + TEST_ENV_OFFSET
    return {
        "torch generators": range(seed, seed + 2),
        "training envs": range(seed, seed + members * num_envs),
        "evaluation envs": range(test, test + members * test_episodes),
        "replay tables": range(seed * TABLE_FACTOR, seed * TABLE_FACTOR + members),
    }


def check(group: int, base: int, members: int, num_envs: int, test_episodes: int) -> None:
    """Raise UsageError unless group `group` keeps to its own seeds (module docstring)."""
    if not 0 <= group <= MAX_GROUP:
        raise UsageError(f"--seed-group must be 0..{MAX_GROUP}, got {group}")
    if not 0 <= base < STRIDE:
        raise UsageError(
            f"--seed-group: run.seed {base} must be 0..{STRIDE - 1} (group G trains with "
            f"run.seed + G * {STRIDE})"
        )
    seed = group_seed(group, base)
    for kind, used in streams(seed, members, num_envs, test_episodes).items():
        scale = TABLE_FACTOR if kind == "replay tables" else 1
        low, high = group * STRIDE * scale, (group + 1) * STRIDE * scale
        if used.start < low or used.stop > high:
            raise UsageError(
                f"--seed-group {group}: its {kind} would be seeded {used.start}..{used.stop - 1}, "
                f"past its window {low}..{high - 1}, so they could share seeds with another "
                f"group ({members} seeds, run.num_envs {num_envs}, run.test_episodes "
                f"{test_episodes}, run.seed {base}): use fewer seeds per group"
            )


def group_logs(log_dir: Path, key: str) -> dict[int, Path]:
    """The non-empty evaluation logs of every seed group of the pair `key` (its group-0
    key), by group."""
    found = {}
    pattern = re.compile(re.escape(key) + r"(?:\.g([1-9][0-9]*))?\.jsonl")
    for path in Path(log_dir).glob("*.jsonl"):
        m = pattern.fullmatch(path.name)
        if m and path.read_text().strip():
            found[int(m.group(1) or 0)] = path
    return dict(sorted(found.items()))


def others_logged(log_dir: Path, key: str, groups: list[dict]) -> bool:
    """Whether `log_dir` holds logs of seed groups of the pair `key` other than `groups`
    (a curve's, [{group, ...}]; none: group 0)."""
    return bool(set(group_logs(log_dir, key)) - ({g["group"] for g in groups} or {0}))


def read_rows(path: Path, until: int | None = None) -> list[dict]:
    """An evaluation log's rows; with `until`, up to the first at or past `until` env steps."""
    rows = [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
    if until is not None:
        end = next((i for i, r in enumerate(rows) if r["t_env"] >= until), len(rows) - 1)
        rows = rows[: end + 1]
    return rows


def _check_aligned(groups: dict[int, list[dict]], k: int, label: str) -> None:
    """Evaluations 0..k-1 of every group must pair up by index: each group's k-th before
    every group's (k+1)-th."""
    for i in range(k - 1):
        if max(g[i]["t_env"] for g in groups.values()) >= min(
            g[i + 1]["t_env"] for g in groups.values()
        ):
            at = {n: g[i]["t_env"] for n, g in groups.items()}
            raise UsageError(
                f"{label}: the seed groups' evaluation {i} is at t_env {at}, so their "
                "evaluations do not pair up: were they run with different --test-interval? "
                "Summarise them apart (move one group's log out of OUT/evals)"
            )


def _merged_row(rows: list[dict], seeds: list[int]) -> dict:
    """One evaluation of every group as one (module docstring)."""
    row = {k: v for k, v in rows[0].items() if k in ("env", "algo")}
    row["t_env"] = max(r["t_env"] for r in rows)
    row["wall_s"] = max(float(r["wall_s"]) for r in rows)
    for key in PER_SEED:
        if all(key in r for r in rows):
            row[key] = [v for r in rows for v in r[key]]
    scalars = set.intersection(*(set(r) for r in rows)) - set(row) - {"commit", *PER_SEED}
    for key in sorted(scalars):
        values = [r[key] for r in rows]
        if all(isinstance(v, int | float) for v in values):
            row[key] = sum(v * n for v, n in zip(values, seeds, strict=True)) / sum(seeds)
    return row


def _seeds(row: dict) -> int:
    return len(next(row[k] for k in PER_SEED if k in row))


def merge(groups: dict[int, list[dict]], label: str) -> tuple[list[dict], dict]:
    """A pair's evaluation rows by seed group -> (the merged rows, what went in: {"groups":
    [{group, seeds, evaluations}], "commits"}). One group's rows come back as they are."""
    seeds = [_seeds(rows[0]) for rows in groups.values()]
    info = {
        "groups": [
            {"group": g, "seeds": n, "evaluations": len(rows)}
            for (g, rows), n in zip(groups.items(), seeds, strict=True)
        ],
        "commits": list(
            dict.fromkeys(r["commit"] for rows in groups.values() for r in rows if "commit" in r)
        ),
    }
    if len(groups) == 1:
        return next(iter(groups.values())), info
    k = min(len(rows) for rows in groups.values())
    _check_aligned(groups, k, label)
    if any(len(rows) != k for rows in groups.values()):
        shortest = min(groups, key=lambda g: len(groups[g]))
        log.warning(
            "%s: seed groups have %s evaluations; summarised up to the shortest, group %d's "
            "(%d evaluations, to t_env %d)",
            label,
            {g: len(rows) for g, rows in groups.items()},
            shortest,
            k,
            groups[shortest][k - 1]["t_env"],
        )
    merged = [_merged_row([rows[i] for rows in groups.values()], seeds) for i in range(k)]
    return merged, info


def load(
    log_dir: Path,
    key: str,
    label: str,
    until: int | None = None,
    finished_at: int | None = None,
):
    """The merged rows and info (`merge`) of every seed group's log of the pair `key`, or
    None when it has none. With `finished_at`, only the groups whose log reaches that many env
    steps (the pair's run.t_max) are merged: a group still training into the same --out, or
    stopped, is left out (logged) rather than cut every other group short."""
    rows = {g: read_rows(p, until) for g, p in group_logs(log_dir, key).items()}
    if finished_at is not None:
        for g in [g for g, r in rows.items() if r[-1]["t_env"] < finished_at]:
            log.warning(
                "%s: seed group %d's log ends at t_env %d of %d (still training, or stopped): "
                "left out of this summary; `--summarise-only` merges it, up to the shortest "
                "group",
                label,
                g,
                rows.pop(g)[-1]["t_env"],
                finished_at,
            )
    if not rows:
        return None
    return merge(rows, label)


def with_finished_groups(
    curves: list[Any],
    log_dir: Path,
    t_max: dict[tuple[str, str], int],
    place: Callable[[Any], str],
    load_pair: Callable[..., Any],
) -> list[Any]:
    """The curves a run trained, each replaced by the merge of its pair's finished seed groups
    where other groups have logs in `log_dir`: `load_pair(log_dir, algo, place(curve),
    finished_at=t_max[(place(curve), algo)])`, `place` being the curve's env (or game). A group
    still training is left out (`load`); with no other group finished, the curve stays."""

    def merged(c: Any) -> Any:
        where = place(c)
        if not others_logged(log_dir, Pair(c.algo, where).key, c.groups):
            return c
        every = load_pair(log_dir, c.algo, where, finished_at=t_max[(where, c.algo)])
        return every if every is not None and len(every.groups) > 1 else c

    return [merged(c) for c in curves]

"""The "table52" entry of `credit repro emcac`'s summary.json (`cluster.repro.table52`) as
markdown, OUT/table52.md, for a results README to include: ours beside the dissertation's
Table 5.2 in its format (median/mean win rate, %), the runs behind each cell and the
ordering claims with their numbers."""

from __future__ import annotations

from pathlib import Path

from cluster.repro.curves import LAST, Curve
from cluster.repro.table52 import ALGOS, CLOSE, EPS, MIN_STEPS, NAMES, table52

FILE = "table52.md"


def pct(x: float) -> str:
    return f"{100 * x:.0f}"


def steps(t: int) -> str:
    return f"{t / 1e6:.2f}M" if t >= 100_000 else f"{t / 1e3:.0f}k"


def short_commit(commit: str) -> str:
    """A commit as the evaluation log records it, shortened: 7 hex digits, and "-dirty"
    where tracked files were modified."""
    return commit[:7] + ("-dirty" if commit.endswith("-dirty") else "")


def cell_text(c: dict | None, theirs: str) -> str:
    """'ours median/mean [interval] vs theirs', or '— not run (vs theirs)'."""
    if c is None:
        return f"— not run (vs {theirs})"
    ci = c["ci_mean"]
    spread = f" [{pct(ci[0])}–{pct(ci[1])}]" if ci is not None else " [1 seed]"
    short = "*" if c["t_env"] < MIN_STEPS else ""
    return f"{pct(c['median'])}/{pct(c['mean'])}{spread}{short} vs {theirs}"


def _table(t: dict) -> list[str]:
    lines = ["| map | " + " | ".join(NAMES[a] for a in ALGOS) + " |"]
    lines.append("|---" * (len(ALGOS) + 1) + "|")
    for m, row in t["cells"].items():
        cells = [cell_text(row[a], t["dissertation"][m][a]) for a in ALGOS]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return lines


def _runs(t: dict) -> list[str]:
    lines = [
        "| map | algorithm | seeds | each seed's last-10 mean (%) | 25–75% | env steps "
        "| evaluations | KL-masked fraction | commits |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for m, row in t["cells"].items():
        for a, c in row.items():
            if c is None:
                continue
            kl = "—" if c["kl_masked_fraction"] is None else f"{c['kl_masked_fraction']:.3f}"
            commits = ", ".join(short_commit(x) for x in c["commits"])
            lines.append(
                f"| {m} | {NAMES[a]} | {c['seeds']} | {', '.join(pct(v) for v in c['per_seed'])} "
                f"| {pct(c['iqr'][0])}–{pct(c['iqr'][1])} | {steps(c['t_env'])} "
                f"| {c['evaluations']} | {kl} | {commits} |"
            )
    return lines


def _verdict(claim: dict) -> str:
    if claim["verdict"] == "missing":
        text = "not yet answerable: not run " + ", ".join(claim["missing"])
    elif claim["verdict"] == "inconclusive":
        text = "inconclusive: an interval straddles the bound (more seeds could decide it)"
    else:
        text = claim["verdict"]
    if claim["under_min_steps"]:
        text += (
            f" (under {MIN_STEPS / 1e6:.0f}M steps: " + ", ".join(claim["under_min_steps"]) + ")"
        )
    return text


def _points(fraction: float) -> str:
    """A difference of win rates in signed points: whole points, but one significant digit
    under one point, so that a difference of one won episode is not printed as "-0" (or
    "+0"). Within the verdicts' float slack of 0 (a bootstrap bound of +3e-15) it is 0."""
    v = 100 * fraction
    if abs(fraction) <= EPS:
        return "0"
    return f"{v:+.1g}" if abs(v) < 0.95 else f"{v:+.0f}"


def _test_text(x: dict) -> str:
    name = f"{x['map']} {NAMES[x['a']]} − {NAMES[x['b']]}"
    ci = x["interval"]
    spread = "" if ci is None else f" [{_points(ci[0])}, {_points(ci[1])}]"
    return f"{name} {_points(x['difference'])}{spread}: {x['verdict']}"


def _claims(t: dict) -> list[str]:
    """One row per claim; its comparisons with a cell not run are named in the verdict."""
    lines = ["| claim | verdict | mean difference, points [95% interval] |", "|---|---|---|"]
    for c in t["claims"]:
        tests = "; ".join(_test_text(x) for x in c["tests"] if x["difference"] is not None)
        lines.append(f"| {c['claim']} | {_verdict(c)} | {tests or '—'} |")
    return lines


def render(t: dict) -> str:
    """The markdown of a "table52" entry."""
    bs = t["bootstrap"]
    head = [
        "<!-- written by `credit repro emcac` (cluster/repro/table52_md.py); rebuilt by "
        "--summarise-only: do not edit -->",
        f"Test win rate (%) over the last {LAST} evaluations: ours, the median/mean over seeds of "
        f"each seed's mean [percentile bootstrap {bs['confidence']:.0%} interval of the mean, "
        f"{bs['reps']} draws, seed {bs['seed']}; with 3 seeds or fewer, the seeds' range], vs "
        f"{t['source']}, median/mean as printed "
        f"({t['dissertation_steps'] / 1e6:.0f}M env steps). —: not run; *: fewer than "
        f"{MIN_STEPS / 1e6:.0f}M env steps.",
        "",
    ]
    claims = [
        "",
        f"Ordering claims. A ≥ B holds when the bootstrap {bs['confidence']:.0%} interval of "
        "mean(A) − mean(B) over both cells' seeds lies at or above 0 and does not hold when it "
        f"lies below 0; A close to B holds when it lies within ±{pct(CLOSE)} points and does "
        "not hold when it lies wholly outside; otherwise the seeds cannot answer yet. A claim "
        "does not hold if one comparison does not.",
        "",
        *_claims(t),
    ]
    notes = []
    if t["dissertation_impossible_cells"]:
        notes = [
            "",
            "As printed, the dissertation's cells "
            + ", ".join(t["dissertation_impossible_cells"])
            + " cannot be median/mean (a mean of 100 needs every seed at 100, a mean of 0 "
            "every seed at 0); read as mean/median every cell of the table is possible.",
        ]
    body = [*_table(t), "", "Runs behind each cell:", "", *_runs(t)]
    return "\n".join(head + body + claims + notes) + "\n"


def write(curves: list[Curve], out: Path, summary: dict, reps: int, seed: int) -> list[str]:
    """Add summary["table52"] and write OUT/table52.md; returns the file's name."""
    summary["table52"] = table52(curves, reps, seed)
    (out / FILE).write_text(render(summary["table52"]))
    return [FILE]

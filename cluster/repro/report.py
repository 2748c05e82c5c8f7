"""One self-contained HTML page for a reproduction: the aggregate statistics
(`cluster.repro.aggregate`) as tables, the per-map summary cells, and every figure inlined as
a base64 PNG (no file or network reference: the page can be mailed or archived alone).

`write_outputs` is what every `credit repro ...` and `credit report DIR` end with: the
"aggregate" entry of the summary, the aggregate figures and report.html.
"""

from __future__ import annotations

import base64
import html
import io
import time
from pathlib import Path

from cluster.repro import aggregate

STYLE = """body{font-family:sans-serif;margin:24px;max-width:1400px;color:#222}
table{border-collapse:collapse;margin:8px 0 20px}td,th{border:1px solid #ccc;padding:3px 8px;
text-align:right}th:first-child,td:first-child{text-align:left}img{max-width:100%;
border:1px solid #eee;margin:6px 0}.note{color:#555;font-size:90%}"""


def write_outputs(
    out: Path,
    title: str,
    scores: aggregate.Scores,
    summary: dict,
    figures: list[tuple[str, bytes]],
    reps: int = aggregate.REPS,
    seed: int = aggregate.SEED,
) -> Path:
    """Add summary["aggregate"], draw the aggregate figures into `out` and write
    out/report.html with them, the tables and `figures` ((caption, PNG bytes) each)."""
    summary["aggregate"] = agg = aggregate.summarise(scores, reps, seed)
    names = aggregate.plot(scores, agg, out, reps, seed)
    pngs = [(n, (out / n).read_bytes()) for n in names] + figures
    page = render(title, summary, pngs)
    (out / "report.html").write_text(page)
    return out / "report.html"


def figure_png(draw, *args) -> bytes:
    """The PNG bytes that `draw(*args, path)` saves (a plot function that takes a path)."""
    buf = io.BytesIO()
    draw(*args, buf)
    return buf.getvalue()


def _ci(cell: dict, key: str) -> str:
    lo, hi = cell["ci"]
    return f"{cell[key]:.3f} <span class=note>[{lo:.3f}, {hi:.3f}]</span>"


def _aggregate_tables(agg: dict) -> str:
    parts = []
    for metric, m in agg["metrics"].items():
        envs = list(m["per_env"])
        head = "".join(f"<th>{html.escape(g)}</th>" for g in envs)
        rows = []
        for algo, cell in m["across_envs"].items():
            per = "".join(
                f"<td>{_ci(m['per_env'][g][algo], 'iqm')}</td>" if algo in m["per_env"][g]
                else "<td>-</td>"
                for g in envs
            )  # fmt: skip
            rows.append(
                f"<tr><td>{html.escape(algo)}</td>{per}<td>{_ci(cell, 'iqm')} "
                f"<span class=note>{cell['runs']} runs x {len(cell['envs'])} envs</span></td></tr>"
            )
        parts.append(
            f"<h3>IQM of the {html.escape(m['label'])}</h3>"
            f"<table id='iqm-{metric}'><tr><th>algorithm</th>{head}<th>across envs</th></tr>"
            + "".join(rows)
            + "</table>"
        )
        rows = [
            f"<tr><td>P({html.escape(pair)})</td><td>{_ci(v, 'p')}</td>"
            f"<td>{html.escape(', '.join(v['envs']))}</td></tr>"
            for pair, v in m["probability_of_improvement"].items()
        ]
        parts.append(
            f"<h3>Probability of improvement ({html.escape(m['label'])})</h3>"
            f"<table id='poi-{metric}'><tr><th>pair</th><th>probability [95% CI]</th>"
            "<th>envs</th></tr>" + "".join(rows) + "</table>"
        )
    return "\n".join(parts)


def _cell_tables(summary: dict) -> str:
    """summary's {group: {name: {field: scalar}}} cells as one table per group."""
    parts = []
    for group, cells in summary.items():
        if group == "aggregate" or not isinstance(cells, dict):
            continue
        if not all(isinstance(c, dict) for c in cells.values()):
            continue
        fields = list(
            dict.fromkeys(
                k for c in cells.values() for k, v in c.items() if isinstance(v, int | float | None)
            )
        )
        head = "".join(f"<th>{html.escape(f)}</th>" for f in fields)
        rows = "".join(
            f"<tr><td>{html.escape(name)}</td>"
            + "".join(f"<td>{_fmt(c.get(f))}</td>" for f in fields)
            + "</tr>"
            for name, c in cells.items()
        )
        parts.append(f"<h3>{html.escape(group)}</h3><table><tr><th></th>{head}</tr>{rows}</table>")
    return "\n".join(parts)


def _fmt(v) -> str:
    if v is None:
        return "-"
    return f"{v:.3g}" if isinstance(v, float) else str(v)


def render(title: str, summary: dict, pngs: list[tuple[str, bytes]]) -> str:
    agg = summary["aggregate"]
    bs = agg["bootstrap"]
    imgs = "\n".join(
        f"<figure><img alt='{html.escape(cap)}' src='data:image/png;base64,"
        f"{base64.b64encode(data).decode()}'><figcaption>{html.escape(cap)}</figcaption></figure>"
        for cap, data in pngs
    )
    return f"""<!doctype html><html><head><meta charset=utf-8>
<title>{html.escape(title)}</title><style>{STYLE}</style></head><body>
<h1>{html.escape(title)}</h1>
<p class=note>Written {time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())}. Interquartile
means (IQM) with stratified bootstrap {bs["confidence"]:.0%} intervals ({bs["method"]}),
{bs["reps"]} draws, numpy seed {bs["seed"]}, computed with {html.escape(agg["library"])}.
To recompute: {html.escape(bs["recompute"])}.</p>
<h2>Aggregate statistics</h2>
{_aggregate_tables(agg)}
<h2>Figures</h2>
{imgs}
<h2>Per-map summary</h2>
{_cell_tables(summary)}
</body></html>
"""

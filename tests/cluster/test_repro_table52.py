"""Table 5.2 beside the dissertation's (`cluster.repro.table52`, `table52_md`): the cells from
synthetic evaluation logs read by the real loader (seed groups merged), the ordering claims'
verdicts and the cells not run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cluster.cli import main
from cluster.repro import table52
from cluster.repro.curves import load_evals
from cluster.repro.pairs import Pair
from cluster.repro.table52_md import render

REPS = 200


def write_log(
    evals: Path,
    algo: str,
    env: str,
    won: list[list[float]],
    group: int = 0,
    commit: str = "a" * 40,
    kl: list[float] | None = None,
    step: int = 10_000,
) -> None:
    """One pair's (seed group's) evaluation log as `credit repro` writes it: won [K][seeds]."""
    evals.mkdir(parents=True, exist_ok=True)
    rows = []
    for k, w in enumerate(won):
        row = {"env": env, "algo": algo, "t_env": k * step + 7 * group, "won": w}
        row |= {"returns": [10 * x for x in w], "wall_s": float(k), "commit": commit}
        if kl is not None:
            row["kl_masked_fraction"] = kl[k]
        rows.append(json.dumps(row))
    (evals / f"{Pair(algo, env, group).key}.jsonl").write_text("\n".join(rows) + "\n")


# 12 evaluations of 3 seeds: the first two all wins, then seed s wins (s + 1) / 10 at odd and
# 0 at even evaluations. Last 10: 5 odd ones -> seed means 0.05, 0.10, 0.15 (all 12: 0.21, ...).
TWELVE = [[1.0, 1.0, 1.0]] * 2 + [[(s + 1) / 10 * (k % 2) for s in range(3)] for k in range(10)]
KL = [0.9, 0.9] + [0.1 * (k % 2) for k in range(10)]  # last 10: mean 0.05


def test_cells_are_each_seeds_last_10_mean_with_kl_commits_and_steps(tmp_path):
    write_log(tmp_path, "emcac", "skirmish/3s5z", TWELVE, kl=KL, commit="b" * 40)
    write_log(tmp_path, "cac", "skirmish/other", TWELVE)  # not a Table 5.2 map: ignored
    curves = load_evals(tmp_path, ["emcac", "cac"], ["skirmish/3s5z", "skirmish/other"])
    t = table52.table52(curves, REPS, 0)
    c = t["cells"]["3s5z"]["emcac"]
    assert c["per_seed"] == pytest.approx([0.05, 0.10, 0.15])
    assert (c["median"], c["mean"]) == (pytest.approx(0.10), pytest.approx(0.10))
    assert c["iqr"] == pytest.approx([0.075, 0.125])
    assert c["kl_masked_fraction"] == pytest.approx(0.05)
    assert c["t_env"] == 110_000 and c["evaluations"] == 12 and c["last_evaluations"] == 10
    assert c["commits"] == ["b" * 40] and c["seeds"] == 3
    lo, hi = c["ci_mean"]
    assert 0.05 <= lo < 0.10 < hi <= 0.15
    assert t["cells"]["3s5z"]["cac"] is None
    assert all(v is None for m in table52.MAPS if m != "3s5z" for v in t["cells"][m].values())
    # the summary's own Table 5.2 numbers are the same seed means
    write_log(tmp_path, "cac", "skirmish/MMM2", [[0.0, 1.0]] * 3)  # 3 evaluations, no KL
    cac = table52.table52(load_evals(tmp_path, ["cac"], ["skirmish/MMM2"]), REPS, 0)
    cell = cac["cells"]["MMM2"]["cac"]
    assert cell["per_seed"] == [0.0, 1.0] and cell["last_evaluations"] == 3
    assert cell["kl_masked_fraction"] is None


def test_seed_groups_merge_into_one_cell(tmp_path):
    g0 = [[0.2]] * 12
    g1 = [[0.6, 1.0]] * 11  # one evaluation short: merged up to the shorter group
    write_log(tmp_path, "qmix", "skirmish/MMM2", g0, commit="c" * 40)
    write_log(tmp_path, "qmix", "skirmish/MMM2", g1, group=1, commit="d" * 40)
    cell = table52.table52(load_evals(tmp_path, ["qmix"], ["skirmish/MMM2"]), REPS, 0)["cells"]
    c = cell["MMM2"]["qmix"]
    assert c["per_seed"] == pytest.approx([0.2, 0.6, 1.0]) and c["seeds"] == 3
    assert c["evaluations"] == 11 and c["t_env"] == 100_007
    assert [g["group"] for g in c["groups"]] == [0, 1] and c["commits"] == ["c" * 40, "d" * 40]


def _cell(per_seed: list[float]) -> dict:
    return {"per_seed": per_seed, "t_env": 2_000_000}


@pytest.mark.parametrize(
    ("relation", "a", "b", "verdict"),
    [
        ("ge", [0.8, 0.85, 0.9], [0.2, 0.25, 0.3], "holds"),
        ("ge", [0.2, 0.25, 0.3], [0.8, 0.85, 0.9], "does not hold"),
        ("ge", [1.0, 1.0, 1.0], [1.0, 1.0], "holds"),  # equal constants: A >= B
        ("ge", [0.95, 0.95, 0.95], [0.95, 0.95, 0.95, 0.95], "holds"),  # float slack
        # A's mean is higher (0.5 vs 0.45), but its seeds spread over [0, 1]: not answered
        ("ge", [0.0, 0.5, 1.0], [0.4, 0.45, 0.5], "inconclusive"),
        ("ge", [0.9], [0.1, 0.2], "inconclusive"),  # one seed: no interval
        ("close", [0.60, 0.62, 0.64], [0.64, 0.66, 0.68], "holds"),
        ("close", [0.9, 0.92, 0.94], [0.3, 0.32, 0.34], "does not hold"),  # far above
        ("close", [0.3, 0.32, 0.34], [0.9, 0.92, 0.94], "does not hold"),  # far below
        ("close", [0.5, 0.6, 0.7], [0.5, 0.52, 0.54], "inconclusive"),  # straddles +0.1
    ],
)
def test_comparison_verdicts_use_the_interval(relation, a, b, verdict):
    got = table52.compare(relation, _cell(a), _cell(b), REPS, 0)
    assert got["verdict"] == verdict
    assert got["difference"] == pytest.approx(np.mean(a) - np.mean(b))
    if len(a) > 1:
        lo, hi = got["interval"]
        assert lo <= got["difference"] + 1e-12 and got["difference"] <= hi + 1e-12
    assert table52.compare(relation, None, _cell(b), REPS, 0)["verdict"] == "missing"


def _cells(values: dict[tuple[str, str], list[float]]) -> dict:
    """Every map x algorithm; those not in `values` not run."""
    return {
        m: {a: (_cell(values[m, a]) if (m, a) in values else None) for a in table52.ALGOS}
        for m in table52.MAPS
    }


def test_claims_hold_fail_or_name_the_missing_cells():
    hi, mid, low, zero = [0.9, 0.92, 0.94], [0.5, 0.52, 0.54], [0.1, 0.12, 0.14], [0.0] * 3
    v = {}
    for m in ("MMM2", "3s5z"):
        v |= {(m, "emcac"): hi, (m, "ecac"): mid, (m, "cac"): low, (m, "coma"): zero}
    v |= {("MMM2", "qmix"): hi, ("3s5z", "qmix"): [0.92, 0.93, 0.94]}
    v |= {("2c_vs_64zg", a): [1.0] * 3 for a in ("cac", "ecac", "emcac", "qmix")}
    v |= {("2c_vs_64zg", "coma"): low}
    # 1c3s5z: COMA beats CAC clearly, E-CAC and QMIX not run, EM-CAC far above COMA
    v |= {("1c3s5z", "coma"): mid, ("1c3s5z", "cac"): low, ("1c3s5z", "emcac"): hi}
    out = table52.claims(_cells(v), REPS, 0)
    chain, close, coma = out
    assert chain["verdict"] == "holds" and chain["missing"] == []
    assert close["verdict"] == "missing" and close["missing"] == ["1c3s5z QMIX"]
    assert [t["verdict"] for t in close["tests"]] == ["holds", "holds", "holds", "missing"]
    # one comparison that does not hold decides, though 1c3s5z has cells not run
    assert coma["verdict"] == "does not hold"
    assert coma["missing"] == ["1c3s5z E-CAC", "1c3s5z QMIX"]
    failed = [(t["map"], t["a"]) for t in coma["tests"] if t["verdict"] == "does not hold"]
    assert failed == [("1c3s5z", "cac")]
    # the same cells with 1c3s5z's CAC above COMA: nothing fails, so the missing cells decide
    v[("1c3s5z", "cac")] = hi
    assert table52.claims(_cells(v), REPS, 0)[2]["verdict"] == "missing"
    # and with one claim's pair overlapping, the claim is inconclusive, not "holds"
    v[("MMM2", "ecac")] = [0.0, 0.5, 1.0]
    assert table52.claims(_cells(v), REPS, 0)[0]["verdict"] == "inconclusive"


def test_the_dissertations_numbers_and_their_impossible_cells():
    assert table52.DISSERTATION["3s5z"] == {
        "cac": "15/5",
        "ecac": "48/63",
        "emcac": "93/93",
        "coma": "1/0",
        "qmix": "85/90",
    }
    assert table52.printed_pair("29/35") == (0.29, 0.35)
    assert table52.printed_pair("30") == (None, None)
    assert table52.impossible_cells() == [
        "2c_vs_64zg CAC 97/100",
        "2c_vs_64zg E-CAC 95/100",
        "2c_vs_64zg EM-CAC 97/100",
        "2c_vs_64zg QMIX 97/100",
        "3s5z COMA 1/0",
        "1c3s5z E-CAC 95/100",
        "1c3s5z EM-CAC 98/100",
    ]
    # table52.md says every cell is possible read as mean/median
    for row in table52.DISSERTATION.values():
        for text in row.values():
            mean, median = table52.printed_pair(text)
            assert mean is None or mean not in (0.0, 1.0) or mean == median


def test_markdown_shows_ours_beside_theirs_and_cells_not_run(tmp_path):
    dirty = "e" * 40 + "-dirty"
    write_log(tmp_path, "emcac", "skirmish/3s5z", [[0.5, 0.7, 0.9]] * 10, kl=[0.25] * 10)
    write_log(tmp_path, "cac", "skirmish/3s5z", [[0.1, 0.2]] * 120, commit=dirty)
    t = table52.table52(load_evals(tmp_path, ["emcac", "cac"], ["skirmish/3s5z"]), 50, 0)
    md = render(t)
    row = next(x for x in md.splitlines() if x.startswith("| 3s5z |")).split(" | ")
    assert row[1].startswith("15/15 [10–20] vs 15/5")  # 1.19M steps: no "*"
    assert row[3].startswith("70/70 [") and row[3].endswith("]* vs 93/93")  # 90k steps
    assert row[2] == "— not run (vs 48/63)"
    assert "| 3s5z | EM-CAC | 3 | 50, 70, 90 | 60–80 | 90k | 10 | 0.250 | aaaaaaa |" in md
    assert "| 3s5z | CAC | 2 | 10, 20 | 12–18 | 1.19M | 120 | — | eeeeeee-dirty |" in md
    assert "| MMM2 | — not run (vs 29/35) |" in md
    chain = next(x for x in md.splitlines() if x.startswith("| EM-CAC >= E-CAC >= CAC"))
    assert "| not yet answerable: not run 3s5z E-CAC, MMM2 CAC, MMM2 E-CAC, MMM2 EM-CAC " in chain
    assert chain.endswith("(under 1M steps: 3s5z EM-CAC) | — |")  # no comparison has both
    # COMA is not run anywhere: its claim names every cell but 3s5z's CAC and EM-CAC
    coma = next(c for c in t["claims"] if c["claim"] == "COMA lowest on every map")
    assert len(coma["missing"]) == 18 and "3s5z CAC" not in coma["missing"]
    assert coma["under_min_steps"] == ["3s5z EM-CAC"]


def test_a_claim_with_every_cell_but_an_undecided_comparison_reads_inconclusive(tmp_path):
    """All cells run (the claim's two maps), one comparison's interval straddles the bound:
    the verdict says inconclusive, not "not yet answerable" (nothing is left to run)."""
    for m in ("skirmish/3s5z", "skirmish/MMM2"):
        write_log(tmp_path, "emcac", m, [[0.6, 0.7, 0.8]] * 10)
        write_log(tmp_path, "ecac", m, [[0.5, 0.6, 0.7]] * 10)
        write_log(tmp_path, "cac", m, [[0.4, 0.6, 0.8]] * 10)  # E-CAC - CAC straddles 0
    algos, maps = ["cac", "ecac", "emcac"], ["skirmish/3s5z", "skirmish/MMM2"]
    t = table52.table52(load_evals(tmp_path, algos, maps), 200, 0)
    chain = next(x for x in render(t).splitlines() if x.startswith("| EM-CAC >= E-CAC >= CAC"))
    assert "| inconclusive: an interval straddles the bound (more seeds could decide it)" in chain


@pytest.mark.slow  # 6 s at load 4 (two cores busy), most of it imports and the plots
def test_summarise_only_with_some_pairs_and_split_seed_groups(tmp_path, capsys):
    """The command end to end on logs alone: a pair split over two seed groups, a pair that
    has not finished, the rest of the table not run."""
    evals = tmp_path / "evals"
    write_log(evals, "cac", "skirmish/3s5z", [[0.2]] * 12)
    write_log(evals, "cac", "skirmish/3s5z", [[0.4, 0.6]] * 12, group=1)
    write_log(evals, "emcac", "skirmish/3s5z", TWELVE[:5], kl=KL[:5])
    argv = ["repro", "emcac", "--out", str(tmp_path), "--summarise-only"]
    argv += ["--envs", "skirmish/3s5z,skirmish/MMM2", "--algos", "cac,emcac,coma"]
    assert main([*argv, "--bootstrap-reps", "20"]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    cells = summary["table52"]["cells"]
    assert cells["3s5z"]["cac"]["per_seed"] == pytest.approx([0.2, 0.4, 0.6])
    assert cells["3s5z"]["emcac"]["evaluations"] == 5 and cells["MMM2"]["cac"] is None
    assert summary["skirmish/3s5z"]["cac"]["seeds"] == 3
    md = (tmp_path / "table52.md").read_text()
    assert "| 3s5z | CAC | 3 | 20, 40, 60 |" in md and "— not run (vs 0/0)" in md
    assert "table52.md" in capsys.readouterr().out


def test_small_differences_keep_their_sign_and_a_decimal():
    """One won greedy episode in a cell's last 10 evaluations is 1/600 of a 3-seed mean: its
    difference reads -0.2 points, not "-0"; smaller ones keep a significant digit, and an
    exact 0 has no sign."""
    from cluster.repro.table52_md import _points

    assert _points(-1 / 600) == "-0.2"
    assert _points(0.0) == _points(-0.0) == _points(3e-17) == _points(-3e-17) == "0"
    assert _points(0.004) == "+0.4" and _points(0.0004) == "+0.04"
    assert _points(0.38) == "+38" and _points(-0.12) == "-12"

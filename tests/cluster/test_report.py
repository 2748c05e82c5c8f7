"""Aggregate statistics (rliable) in every reproduction and `credit report DIR`: numbers by
hand and recomputed with rliable alone, the committed logs summarised, and the HTML page
opened in headless Chromium."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from cluster.cli import main
from cluster.repro import aggregate
from tests.cluster.browser import chromium, needs_chromium

ROOT = Path(__file__).resolve().parents[2]
REPS = 50  # bootstrap draws in these tests (the commands' default is aggregate.REPS)


def test_iqm_by_hand_and_each_interval_recomputed_with_rliable_alone():
    pytest.importorskip("rliable")
    from rliable import library, metrics

    # 8 runs on one map: the IQM drops the 2 lowest and 2 highest -> mean(0.3..0.6) = 0.45.
    runs = [0.0, 0.1, 0.3, 0.4, 0.5, 0.6, 0.9, 1.0]
    other = [0.2, 0.2, 0.3, 0.3, 0.4, 0.4, 0.5, 0.5]
    scores = {"win_rate": {"m/a": {"x": runs, "y": other}, "m/b": {"x": other, "y": runs}}}
    agg = aggregate.summarise(scores, reps=REPS, seed=7)
    assert agg["bootstrap"] == agg["bootstrap"] | {"reps": REPS, "seed": 7, "confidence": 0.95}
    cell = agg["metrics"]["win_rate"]["per_env"]["m/a"]["x"]
    assert cell["iqm"] == pytest.approx(0.45) and cell["runs"] == 8 and cell["scores"] == runs
    lo, hi = cell["ci"]
    assert lo < 0.45 < hi
    # The summary's recipe, followed with rliable directly.
    across = agg["metrics"]["win_rate"]["across_envs"]["x"]
    matrix = np.asarray([runs, other]).T  # runs x envs
    np.random.seed(7)
    point, ci = library.get_interval_estimates(
        {"x": matrix}, lambda s: np.array([metrics.aggregate_iqm(s)]), reps=REPS
    )
    assert across["iqm"] == pytest.approx(point["x"][0])
    assert across["ci"] == pytest.approx([ci["x"][0][0], ci["x"][1][0]])
    poi = agg["metrics"]["win_rate"]["probability_of_improvement"]["x > y"]
    np.random.seed(7)
    point, ci = library.get_interval_estimates(
        {"p": [matrix, matrix[:, ::-1]]},
        lambda x, y: np.array([metrics.probability_of_improvement(x, y)]),
        reps=REPS,
    )
    assert poi["p"] == pytest.approx(point["p"][0]) and poi["envs"] == ["m/a", "m/b"]
    assert poi["ci"] == pytest.approx([ci["p"][0][0], ci["p"][1][0]])
    # The mirrored maps make x and y equally good overall.
    assert poi["p"] == pytest.approx(0.5)


def test_max_return_per_family():
    assert aggregate.max_return("matrix/two_step", {}) == 8.0
    assert aggregate.max_return("skirmish/3m", {}) == 20.0
    assert aggregate.max_return("skirmish/3m", {"reward_scale_rate": 10}) == 10.0
    assert aggregate.max_return("maps/my_bane.yaml", {}) == 20.0  # a map file is skirmish
    with pytest.raises(ValueError, match="reward_scale=false"):
        aggregate.max_return("skirmish/3m", {"reward_scale": False})


def _copy_evals(src: Path, dst: Path, keep_lines: dict[str, int] = {}) -> Path:  # noqa: B006
    (dst / "evals").mkdir(parents=True)
    for f in (src / "evals").glob("*.jsonl"):
        lines = f.read_text().splitlines()
        n = keep_lines.get(f.name, len(lines))
        (dst / "evals" / f.name).write_text("\n".join(lines[:n]) + "\n")
    return dst


def test_repro_matrix_summarise_only_on_the_committed_logs(tmp_path, capsys):
    out = _copy_evals(ROOT / "results" / "matrix", tmp_path / "m")
    argv = ["repro", "matrix", "--seeds", "8", "--out", str(out), "--summarise-only"]
    assert main([*argv, "--bootstrap-reps", str(REPS)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    agg = summary["aggregate"]["metrics"]["normalised_return"]
    assert set(agg["per_env"]) == {"matrix/two_step", "matrix/four_game"}
    assert set(agg["across_envs"]) == {"iql", "vdn", "qmix", "qmix_ns", "rdn"}
    assert len(agg["probability_of_improvement"]) == 10  # 5 algorithms, each pair once
    assert all(c["runs"] == 8 for c in agg["across_envs"].values())
    # The committed summary's per-cell numbers are unchanged by the new entry; the committed
    # logs predate the per-line commit, so their cells list no commits.
    committed = json.loads((ROOT / "results" / "matrix" / "summary.json").read_text())
    # Each cell also names its seed groups: the committed logs are group 0's.
    for algo in ("iql", "rdn"):
        assert all(cell["commits"] == [] for cell in summary[algo].values())
        for cell in summary[algo].values():
            assert cell.pop("groups") == [{"group": 0, "seeds": 8, "evaluations": 301}]
        assert summary[algo] == {
            g: {**c, "wall_s": summary[algo][g]["wall_s"], "commits": []}
            for g, c in committed[algo].items()
        }
    for name in ("report.html", "aggregate_intervals.png", "aggregate_profiles.png"):
        assert (out / name).stat().st_size > 5_000, name
    assert not (out / "curves.json").exists()  # kept as the training wrote it (not here)


def test_report_without_logs_exits_2(tmp_path, capsys):
    assert main(["report", str(tmp_path)]) == 2
    assert "no evaluation logs" in capsys.readouterr().err
    (tmp_path / "evals").mkdir()
    (tmp_path / "evals" / "x.jsonl").write_text("not json\n")
    assert main(["report", str(tmp_path)]) == 2
    assert "not an evaluation log" in capsys.readouterr().err


@needs_chromium
def test_report_of_a_partial_experiment_opens_in_chromium(tmp_path):
    # results/smac/8m with RDN's log cut to its first 5 evaluations: a run still going.
    out = _copy_evals(ROOT / "results" / "smac" / "8m", tmp_path / "8m", {
        "skirmish-8m__rdn.jsonl": 5
    })  # fmt: skip
    assert main(["report", str(out), "--bootstrap-reps", str(REPS)]) == 0
    page = (out / "report.html").read_text()
    assert "src='data:image/png;base64," in page and "http" not in page  # self-contained
    shutil.copy(out / "report.html", tmp_path / "alone.html")  # nothing beside it
    with chromium(1400, 1000) as driver:
        driver.get((tmp_path / "alone.html").as_uri())
        images = driver.execute_script(
            "return Array.from(document.images).map(i => [i.alt, i.naturalWidth]);"
        )
        rows = driver.execute_script(
            "return Array.from(document.querySelectorAll('#iqm-win_rate tr')).slice(1)"
            ".map(r => Array.from(r.cells).map(c => c.innerText));"
        )
        poi = driver.execute_script("return document.querySelectorAll('#poi-win_rate tr').length")
    assert [alt for alt, _ in images][:2] == ["aggregate_intervals.png", "aggregate_profiles.png"]
    assert "skirmish/8m: learning curves" in [alt for alt, _ in images]
    assert all(width > 300 for _, width in images), images  # every PNG decoded
    assert poi == 1 + 10
    agg = aggregate_of(out)["metrics"]["win_rate"]["across_envs"]
    shown = {r[0]: r[-1] for r in rows}
    assert set(shown) == set(agg)
    for algo, cell in agg.items():
        assert shown[algo].startswith(f"{cell['iqm']:.3f} [{cell['ci'][0]:.3f}, ")


def aggregate_of(out: Path) -> dict:
    """The aggregate a report wrote: report.html's numbers come from the same dict; without a
    summary.json (a partial run) recompute it the report's way."""
    from cluster.repro.curves import LAST, load_evals

    curves = load_evals(out / "evals", ["iql", "qmix", "qmix_ns", "rdn", "vdn"], ["skirmish/8m"])
    scores = aggregate.curve_scores(curves, {"skirmish/8m": 20.0}, LAST)
    return aggregate.summarise(scores, reps=REPS)

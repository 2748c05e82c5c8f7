"""Rendered episodes (`credit env render`, the demo's GIF) framed on the battle, not the map."""

from __future__ import annotations

import numpy as np
from PIL import Image

from actors.envs.registry import make_vec_env
from actors.envs.skirmish.render import MARGIN, MIN_SPAN, battle_view, snapshot
from cluster.cli import main

BLUE, RED = (31, 119, 180), (214, 39, 40)  # matplotlib's tab:blue and tab:red (the teams)


def test_the_view_holds_every_unit_with_a_margin_inside_the_map():
    venv = make_vec_env("skirmish/3m", 1, seed=0)
    venv.reset()
    snap = snapshot(venv)
    x0, x1, y0, y1 = battle_view([snap])
    assert x1 - x0 == y1 - y0 >= MIN_SPAN  # square, at least the narrowest view
    assert x0 <= snap["x"].min() - MARGIN and snap["x"].max() + MARGIN <= x1
    assert y0 <= snap["y"].min() - MARGIN and snap["y"].max() + MARGIN <= y1
    assert x1 - x0 < snap["map"][0] / 2  # 3m's six units: well under half the 32-wide map
    moved = {**snap, "x": snap["x"] * 0 + 31.5}  # units at the map's edge: drawn whole
    x0, x1, _, _ = battle_view([snap, moved])
    assert 31.5 + MARGIN <= x1 <= snap["map"][0] + MARGIN and x0 >= -MARGIN


def _team_pixels(frame: np.ndarray, color: tuple[int, int, int]) -> np.ndarray:
    return np.argwhere(np.abs(frame.astype(int) - color).sum(-1) < 40)


def test_rendered_3m_battle_spans_most_of_the_frame(tmp_path):
    out = tmp_path / "3m.gif"
    assert main(["env", "render", "--env", "skirmish/3m", "--out", str(out)]) == 0
    gif = Image.open(out)
    frame = np.asarray(gif.convert("RGB"))  # t=0: both teams lined up
    assert frame.shape == (400, 400, 3)
    blue, red = _team_pixels(frame, BLUE), _team_pixels(frame, RED)
    assert len(blue) > 300 and len(red) > 300  # the units are drawn large enough to see
    left, right = blue[:, 1].min(), red[:, 1].max()
    # Framed on the whole 32-wide map the two lines stood ~90 px apart in the 400 px frame.
    assert right - left > 200, (left, right)

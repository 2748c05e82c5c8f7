"""Drawing skirmish battles: frames of a battle's states, written as an animated GIF (or a PNG
strip of frames). Playing the episodes to draw is `actors.episode_gifs`'s job.

Allies are blue, enemies red; the marker shape is the unit type, a bar above each unit its
health (+ shield, cyan); a line from attacker to target marks who fired during the step;
dead units are small grey crosses. An episode's frames are framed on its battle: one square
view around every position its units take (`battle_view`), not the whole map, in which a
3m battle filled about a tenth of the frame.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from actors.envs.skirmish.env import SkirmishVecEnv

log = logging.getLogger(__name__)
MARKERS = {
    "marine": "o",
    "marauder": "s",
    "medivac": "P",
    "stalker": "D",
    "zealot": "^",
    "colossus": "*",
    "zergling": "v",
    "baneling": "h",
    "hydralisk": "p",
}


def statics(venv: SkirmishVecEnv, m: int = 0) -> dict[str, Any]:
    """What stays fixed during an episode of battle m: its units and the map."""
    ro = venv.battle.roster(m)
    return {
        "names": ro.names, "team": ro.team, "radius": ro.radius, "hp_max": ro.hp_max,
        "sh_max": ro.sh_max, "map": (venv.st.map_w, venv.st.map_h),
    }  # fmt: skip


def dynamics(venv: SkirmishVecEnv, m: int = 0) -> dict[str, np.ndarray]:
    """Battle m's unit state now (copied): x, y, hp, sh, alive, tgt (last target, -1 none)."""
    b = venv.battle
    return {
        "x": b.x[m].copy(), "y": b.y[m].copy(), "hp": b.hp[m].copy(), "sh": b.sh[m].copy(),
        "alive": b.alive[m].copy(), "tgt": b.last_tgt[m].copy(),
    }  # fmt: skip


def snapshot(venv: SkirmishVecEnv, m: int = 0) -> dict[str, Any]:
    """What a frame of battle m shows (`statics` and `dynamics`), so it can be drawn later."""
    return {**statics(venv, m), **dynamics(venv, m)}


MARGIN = 2.0  # map units around the battle (the health bars sit 0.9 above a unit)
MIN_SPAN = 10.0  # the narrowest view, in map units


def battle_view(snaps: list[dict[str, Any]]) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1): the square around every unit's position in `snaps` (one episode)
    plus MARGIN, at least MIN_SPAN wide, inside the map (widened by MARGIN) where it fits."""
    xs = np.concatenate([np.asarray(s["x"], float) for s in snaps])
    ys = np.concatenate([np.asarray(s["y"], float) for s in snaps])
    map_w, map_h = snaps[0]["map"]
    span = max(MIN_SPAN, xs.max() - xs.min() + 2 * MARGIN, ys.max() - ys.min() + 2 * MARGIN)
    cx, cy = (xs.max() + xs.min()) / 2, (ys.max() + ys.min()) / 2
    # inside the map but for the margin (a unit at the edge is drawn whole)
    x0 = min(max(cx - span / 2, -MARGIN), max(map_w + MARGIN - span, -MARGIN))
    y0 = min(max(cy - span / 2, -MARGIN), max(map_h + MARGIN - span, -MARGIN))
    return x0, x0 + span, y0, y0 + span


class FrameDrawer:
    """Draws snapshots of one battle's units on a single figure kept across frames: the map,
    axes and legend are made once and only the units change (a new figure per frame costs
    several times more, mostly in laying out its ticks).

        drawer = FrameDrawer(first_snapshot, view=battle_view(snaps))
        frames = [drawer.draw(snap, f"t={t}") for t, snap in enumerate(snaps)]
        drawer.close()

    `view` (x0, x1, y0, y1) is the part of the map shown; None shows the whole map.
    """

    def __init__(self, snap: dict[str, Any], view: tuple[float, ...] | None = None):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        self.plt = plt
        self.fig, ax = plt.subplots(figsize=(5, 5), dpi=80)
        x0, x1, y0, y1 = view or (0.0, snap["map"][0], 0.0, snap["map"][1])
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_aspect("equal")
        # points per map unit: a unit's marker is drawn at least its true size
        self.pt_per_unit = ax.get_position().width * 5 * 72 / (x1 - x0)
        ax.tick_params(labelsize=6)
        names = snap["names"]
        handles = [
            ax.plot([], [], MARKERS.get(n, "o"), color="0.4", label=n)[0]
            for n in sorted(set(names))
        ]
        ax.legend(handles=handles, loc="lower left", fontsize=6, framealpha=0.6)
        self.ax = ax
        self.static = list(ax.lines)
        self.title = ax.set_title("", fontsize=9)
        self.note = ax.text(0.01, 0.99, "", transform=ax.transAxes, fontsize=6, va="top")

    def draw(
        self,
        snap: dict[str, Any],
        title: str,
        tint: dict[int, Any] | None = None,
        note: str = "",
    ) -> np.ndarray:
        """An RGB image [H, W, 3] (uint8) of a `snapshot` of the battle given to __init__;
        `tint` maps unit indices to colours that replace their team colour (e.g. each agent's
        share of the credit), `note` is a line of text at the top left."""
        ax, s, team, names = self.ax, snap, snap["team"], snap["names"]
        for line in [line for line in ax.lines if line not in self.static]:
            line.remove()
        self.note.set_text(note)
        self.title.set_text(title)
        for u, t in enumerate(s["tgt"].tolist()):
            if t >= 0:
                color = "tab:green" if team[u] == team[t] else "orange"
                ax.plot([s["x"][u], s["x"][t]], [s["y"][u], s["y"][t]], color=color, lw=0.8)
        for u in range(len(names)):
            x, y = s["x"][u], s["y"][u]
            if not s["alive"][u]:
                ax.plot(x, y, "x", color="0.7", ms=3)
                continue
            color = "tab:blue" if team[u] == 0 else "tab:red"
            if tint and u in tint:
                color = tint[u]
            size = max(4 + 8 * s["radius"][u], 1.6 * s["radius"][u] * self.pt_per_unit)
            ax.plot(x, y, MARKERS.get(names[u], "o"), color=color, ms=size, mec="k", mew=0.4)
            bar = y + max(0.7, s["radius"][u] + 0.3)  # above the marker
            frac = s["hp"][u] / s["hp_max"][u]
            ax.plot([x - 0.5, x - 0.5 + frac], [bar, bar], color="limegreen", lw=1.5)
            if s["sh_max"][u] > 0:
                sf = s["sh"][u] / s["sh_max"][u]
                ax.plot([x - 0.5, x - 0.5 + sf], [bar + 0.2, bar + 0.2], color="cyan", lw=1.2)
        self.fig.canvas.draw()
        return np.asarray(self.fig.canvas.buffer_rgba())[..., :3].copy()

    def close(self) -> None:
        self.plt.close(self.fig)


def draw_frame(
    snap: dict[str, Any], title: str, tint: dict[int, Any] | None = None, note: str = ""
) -> np.ndarray:
    """An RGB image [H, W, 3] (uint8) of a `snapshot` (one frame; `FrameDrawer` for many);
    `tint` and `note` as in `FrameDrawer.draw`."""
    drawer = FrameDrawer(snap)
    try:
        return drawer.draw(snap, title, tint, note)
    finally:
        drawer.close()


def write_images(frames: list[np.ndarray], out: str | Path) -> Path:
    """`.gif`: an animation of `frames`; anything else: a strip of up to 8 of them."""
    from PIL import Image

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(f) for f in frames]
    if out.suffix.lower() == ".gif":
        images[0].save(out, save_all=True, append_images=images[1:], duration=150, loop=0)
    else:
        step = max(1, len(images) // 8)
        pick = images[::step][:8]
        w, h = pick[0].size
        strip = Image.new("RGB", (w * len(pick), h), "white")
        for i, im in enumerate(pick):
            strip.paste(im, (i * w, 0))
        strip.save(out)
    log.info("wrote %s (%d frames)", out, len(frames))
    return out

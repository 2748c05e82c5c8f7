"""Replays of skirmish episodes as animated GIFs (or a PNG strip of frames).

Allies are blue, enemies red; the marker shape is the unit type, a bar above each unit its
health (+ shield, cyan); a line from attacker to target marks who fired during the step;
dead units are small grey crosses.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from actors.envs.registry import make_vec_env
from actors.envs.skirmish.env import SkirmishVecEnv
from actors.envs.skirmish.scripts import POLICIES

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


def _frame(venv: SkirmishVecEnv, title: str) -> np.ndarray:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    b, st = venv.battle, venv.st
    fig, ax = plt.subplots(figsize=(5, 5), dpi=80)
    ax.set_xlim(0, st.map_w)
    ax.set_ylim(0, st.map_h)
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=9)
    ax.tick_params(labelsize=6)
    for u in range(st.U):
        if b.last_fire[0, u] and b.last_tgt[0, u] >= 0:
            t = b.last_tgt[0, u]
            color = "tab:green" if st.team[u] == st.team[t] else "orange"
            ax.plot([b.x[0, u], b.x[0, t]], [b.y[0, u], b.y[0, t]], color=color, lw=0.8)
    for u in range(st.U):
        x, y = b.x[0, u], b.y[0, u]
        if not b.alive[0, u]:
            ax.plot(x, y, "x", color="0.7", ms=3)
            continue
        color = "tab:blue" if st.team[u] == 0 else "tab:red"
        size = 4 + 8 * st.radius[u]
        ax.plot(x, y, MARKERS.get(st.names[u], "o"), color=color, ms=size, mec="k", mew=0.4)
        frac = b.hp[0, u] / st.hp_max[u]
        ax.plot([x - 0.5, x - 0.5 + frac], [y + 0.7, y + 0.7], color="limegreen", lw=1.5)
        if st.sh_max[u] > 0:
            sf = b.sh[0, u] / st.sh_max[u]
            ax.plot([x - 0.5, x - 0.5 + sf], [y + 0.9, y + 0.9], color="cyan", lw=1.2)
    handles = [
        ax.plot([], [], MARKERS.get(n, "o"), color="0.4", label=n)[0] for n in sorted(set(st.names))
    ]
    ax.legend(handles=handles, loc="lower left", fontsize=6, framealpha=0.6)
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return img


def render_episode(
    env_id: str,
    out: str | Path,
    policy: str = "nearest",
    seed: int = 0,
    max_steps: int = 120,
    **env_args: Any,
) -> dict[str, Any]:
    """Play one episode of `env_id` with a scripted `policy` and write it to `out`.

    Args:
        env_id: a skirmish env id.
        out: `.gif` for an animation, anything else (e.g. `.png`) for a strip of frames.
        policy: a name in `scripts.POLICIES`.
        seed / max_steps: episode seed and frame cap.

    Returns:
        {"out", "frames", "battle_won", "steps", "return"}.
    """
    from PIL import Image

    venv = make_vec_env(env_id, 1, seed=seed, **env_args)
    if not isinstance(venv, SkirmishVecEnv):
        raise ValueError(f"render needs a skirmish env, got {env_id}")
    act = POLICIES[policy]
    rng = np.random.default_rng(seed)
    venv.reset()
    frames = [_frame(venv, f"{env_id}  t=0")]
    ret, won, t = 0.0, False, 0
    while t < max_steps:
        r, term, infos = venv.step(act(venv, rng), np.ones(1, bool))
        t += 1
        ret += float(r[0])
        frames.append(_frame(venv, f"{env_id}  t={t}  return={ret:.1f}"))
        if term[0]:
            won = bool(infos[0]["battle_won"])
            break
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
    return {"out": str(out), "frames": len(frames), "battle_won": won, "steps": t, "return": ret}

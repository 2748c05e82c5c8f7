"""Whole skirmish episodes as animated GIFs (or PNG strips): played by a scripted policy
(`render_episode`, for `credit env render`) or by a learnt one (`render_policy_episode`, for
run reports), drawn by `actors.envs.skirmish.render`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from actors.envs.registry import make_vec_env
from actors.envs.skirmish.env import SkirmishVecEnv
from actors.envs.skirmish.render import FrameDrawer, battle_view, snapshot, write_images
from actors.envs.skirmish.scripts import POLICIES
from actors.rollout import RolloutWorker


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
    venv = make_vec_env(env_id, 1, seed=seed, **env_args)
    if not isinstance(venv, SkirmishVecEnv):
        raise ValueError(f"render needs a skirmish env, got {env_id}")
    act = POLICIES[policy]
    rng = np.random.default_rng(seed)
    venv.reset()
    snaps, titles = [snapshot(venv)], [f"{env_id}  t=0"]
    ret, won, t = 0.0, False, 0
    while t < max_steps:
        r, term, infos = venv.step(act(venv, rng), np.ones(1, bool))
        t += 1
        ret += float(r[0])
        snaps.append(snapshot(venv))
        titles.append(f"{env_id}  t={t}  return={ret:.1f}")
        if term[0]:
            won = bool(infos[0]["battle_won"])
            break
    drawer = FrameDrawer(snaps[0], view=battle_view(snaps))
    frames = [drawer.draw(snap, title) for snap, title in zip(snaps, titles, strict=True)]
    drawer.close()
    out = write_images(frames, out)
    return {"out": str(out), "frames": len(frames), "battle_won": won, "steps": t, "return": ret}


def render_policy_episode(
    worker: RolloutWorker, out: str | Path, title: str, tries: int = 10
) -> dict[str, Any]:
    """Play greedy episodes with `worker`'s policy until one is won (at most `tries`) and
    write that one, or the last if none was won, to `out`.

    Args:
        worker: a RolloutWorker over one skirmish env (num_envs 1), holding the policy.
        out: `.gif` for an animation, anything else for a strip of frames.
        title: shown above every frame, before the step and the return so far.
        tries: episodes played at most.

    Returns:
        {"out", "frames", "battle_won", "steps", "return", "episodes_played"}.
    """
    venv = worker.venv
    if not isinstance(venv, SkirmishVecEnv) or venv.num_envs != 1:
        raise ValueError("render_policy_episode needs a worker over one skirmish env")
    snaps: list[dict[str, Any]] = []  # the battle after the reset and after every step
    played = 0
    while played < tries:
        played += 1
        snaps.clear()
        result = worker.run_round(greedy=True, on_step=lambda: snaps.append(snapshot(venv)))
        if result.won[0]:
            break
    won = bool(result.won[0])
    returns = np.concatenate([[0.0], np.cumsum(result.episodes[0].reward)])
    drawer = FrameDrawer(snaps[0], view=battle_view(snaps))
    frames = [
        drawer.draw(snap, f"{title}  t={t}  return={returns[t]:.1f}")
        for t, snap in enumerate(snaps)
    ]
    frames += [drawer.draw(snaps[-1], f"{title}  {'won' if won else 'lost'}")] * 4  # a pause
    drawer.close()
    out = write_images(frames, out)
    steps = len(snaps) - 1
    return {
        "out": str(out),
        "frames": len(frames),
        "battle_won": won,
        "steps": steps,
        "return": float(returns[-1]),
        "episodes_played": played,
    }

"""`credit inspect relevance`: who gets the credit in a trained value-family run.

Plays K greedy episodes with a checkpoint's agents and computes, for every step and agent,
the credit the algorithm hands that agent:

* rdn: the agent's LRP share of the central critic's value for the taken joint action (the
  RDN learner's own `agent_targets`, i.e. the Q target the agent is trained on);
* vdn, iql: the agent's utility Q_i(o_i, u_i) of the action it took (VDN's Q_tot is their sum);
* qmix, qmix_ns: the utility, the mixer's gradient dQ_tot/dQ_i, and as the credit their product
  (the first-order share of Q_tot, as gradient x input), so the methods sit side by side.

Credit is grouped by unit type and by whether the unit is alive at that step. An agent's
share at a step is its credit over the sum of |credit| of all agents then. Outputs (in --out):
relevance.json (every number), relevance.png (credit over time per group, per-agent means,
type shares) and relevance.gif (one episode, each agent tinted by its share).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from actors.envs.registry import make_vec_env
from actors.rollout import RolloutWorker
from buffer_service.episode import Episode, EpisodeBatch
from cluster.config.train import TrainConfig, build_train_config
from cluster.errors import UsageError
from learner.batch import TensorBatch, agent_inputs
from learner.critic_inputs import obs_history
from learner.networks import unroll
from learner.registry import get_algo

log = logging.getLogger(__name__)
ALGOS = ("rdn", "vdn", "iql", "qmix", "qmix_ns")


def find_checkpoint(run: Path) -> Path:
    """The checkpoint folder of a run: RUN/checkpoint (`credit train`) or RUN itself (a
    checkpoint, e.g. a `credit repro ... --checkpoints` pair folder)."""
    for cand in (run / "checkpoint", run):
        if (cand / "learner.pt").exists() and (cand / "config.yaml").exists():
            return cand
    pairs = sorted(p.name for p in (run / "checkpoints").glob("*") if p.is_dir())
    hint = f"; pick one of {run / 'checkpoints'}/{{{','.join(pairs)}}}" if pairs else ""
    raise UsageError(f"--run {run}: no checkpoint (learner.pt + config.yaml) found{hint}")


def member_state(state: Any, member: int, n_ensemble: int) -> Any:
    """One ensemble member of a (nested) state dict: every tensor with a leading E axis is
    sliced to [1, ...]; anything else is kept."""
    if isinstance(state, dict):
        return {k: member_state(v, member, n_ensemble) for k, v in state.items()}
    if isinstance(state, torch.Tensor) and state.dim() and state.shape[0] == n_ensemble:
        return state[member : member + 1].clone()
    return state


def load_member(ckpt: Path, member: int) -> tuple[TrainConfig, Any]:
    """The config and a 1-member learner holding `member`'s networks."""
    cfg = build_train_config(yaml.safe_load((ckpt / "config.yaml").read_text()))
    if cfg.algo_name not in ALGOS:
        raise UsageError(
            f"inspect relevance supports {', '.join(ALGOS)}; {ckpt} is {cfg.algo_name}"
        )
    state = torch.load(ckpt / "learner.pt", weights_only=False)
    n_ensemble = int(next(iter(state["agent"].values())).shape[0])
    if not 0 <= member < n_ensemble:
        raise UsageError(f"--member must be in 0..{n_ensemble - 1} for {ckpt}")
    schema = make_vec_env(cfg.env.id, 1, **cfg.env.args).info.schema()
    learner = get_algo(cfg.algo_name).build(cfg.algo, schema, 1, "cpu")
    one = member_state(state, member, n_ensemble)
    learner.agent.load_state_dict(one["agent"])
    if cfg.algo_name == "rdn":
        learner.critic.load_state_dict(one["critic"])
    elif learner.mixer is not None:
        learner.mixer.load_state_dict(one["mixer"])
    return cfg, learner


class Recorder:
    """A VecEnv that keeps every battle's unit state after reset and after each step
    (`render.snapshot` of each), for drawing and for the alive flags."""

    def __init__(self, venv):
        from actors.envs.skirmish.render import dynamics, statics

        self._venv, self._dynamics = venv, dynamics
        self.statics = [statics(venv, m) for m in range(venv.num_envs)]
        self.frames: list[list[dict]] = [[] for _ in range(venv.num_envs)]

    def __getattr__(self, name: str) -> Any:
        return getattr(self._venv, name)

    def _record(self, which: np.ndarray) -> None:
        for m in np.flatnonzero(which):
            self.frames[m].append(self._dynamics(self._venv, int(m)))

    def reset(self, *args, **kwargs):
        out = self._venv.reset(*args, **kwargs)
        self.frames = [[] for _ in range(self._venv.num_envs)]
        self._record(np.ones(self._venv.num_envs, bool))
        return out

    def step(self, actions, active):
        out = self._venv.step(actions, active)
        self._record(np.asarray(active, bool))
        return out


def play(
    cfg: TrainConfig, learner: Any, episodes: int, seed: int
) -> tuple[list[Episode], list[bool], Recorder]:
    """`episodes` greedy episodes of the learner's agents on the run's env (and whether each
    was won)."""
    from actors.envs.skirmish.env import SkirmishVecEnv

    venv = make_vec_env(cfg.env.id, episodes, seed=seed, **cfg.env.args)
    if not isinstance(venv, SkirmishVecEnv):
        raise UsageError(f"inspect relevance needs a skirmish env, the run used {cfg.env.id}")
    rec = Recorder(venv)
    worker = RolloutWorker(rec, learner.agent, "q", cfg.exploration, 1, seed=seed)
    result = worker.run_round(t_env=0, greedy=True)
    return result.episodes, [bool(w) for w in result.won], rec


def credit(cfg: TrainConfig, learner: Any, episodes: list[Episode]) -> dict[str, np.ndarray]:
    """Per-transition credit [B, T, N] (padded steps zero) and its parts, by algorithm."""
    tb = TensorBatch.from_episodes(EpisodeBatch.from_episodes(episodes))
    _, b, t, n = tb.shape
    out: dict[str, np.ndarray] = {}
    if cfg.algo_name == "rdn":
        with torch.no_grad():
            hist = obs_history(tb.obs, cfg.algo.obs_window)[:, :, :-1]
            shares, q = learner.shares(hist, tb.actions)
        out["credit"] = shares.view(b, t, n).numpy()
        out["q_total"] = q.view(b, t).numpy()
    else:
        qs = unroll(learner.agent, agent_inputs(tb.obs, tb.actions, learner.info.n_actions))
        chosen = qs[:, :, :-1].gather(-1, tb.actions.unsqueeze(-1)).squeeze(-1)
        out["utility"] = chosen.detach().view(b, t, n).numpy()
        if learner.mixer is None:
            out["credit"] = out["utility"]
            if cfg.algo_name == "vdn":
                out["q_total"] = out["utility"].sum(-1)
        else:
            cond = learner._cond(tb)[:, :, :-1]
            u = chosen.detach().requires_grad_(True)
            q_tot = learner._mix(learner.mixer, u, cond)
            (grad,) = torch.autograd.grad(q_tot.sum(), u)  # transitions do not interact
            out["mixer_grad"] = grad.view(b, t, n).numpy()
            out["credit"] = out["mixer_grad"] * out["utility"]
            out["q_total"] = q_tot.detach().view(b, t).numpy()
    mask = tb.mask.view(b, t).numpy().astype(bool)
    for key in out:
        out[key] = np.where(mask.reshape(b, t, *([1] * (out[key].ndim - 2))), out[key], 0.0)
    out["mask"] = mask
    return out


def summarise(
    cfg: TrainConfig,
    names: list[str],
    parts: dict[str, np.ndarray],
    alive: np.ndarray,
    episodes: list[Episode],
    won: list[bool],
) -> dict:
    """Every number of the outputs: credit per (type, alive) group, per type and per agent,
    over time, and per episode. `alive` [B, T, N]: the unit is alive when the step starts."""
    c, mask = parts["credit"], parts["mask"]
    n = c.shape[-1]
    denom = np.abs(c).sum(-1, keepdims=True)
    share = np.where(denom > 0, c / np.where(denom > 0, denom, 1.0), 0.0)
    kinds = np.array(names)
    groups, over_time = {}, {}
    for kind in sorted(set(names)):
        for state, flag in (("alive", True), ("dead", False)):
            sel = mask[..., None] & (alive == flag) & (kinds == kind)[None, None]
            if not sel.any():
                continue
            key = f"{kind}/{state}"
            groups[key] = {
                "mean_credit": float(c[sel].mean()),
                "mean_share": float(share[sel].mean()),
                "agent_steps": int(sel.sum()),
            }
            counts = sel.sum(axis=(0, 2))
            sums = np.where(sel, c, 0.0).sum(axis=(0, 2))
            over_time[key] = [
                round(float(s / k), 5) if k else None for s, k in zip(sums, counts, strict=True)
            ]
    per_type = {}
    for kind in sorted(set(names)):
        cols = kinds == kind
        live = mask[..., None] & alive & cols[None, None]
        per_type[kind] = {
            "agents": int(cols.sum()),
            "mean_credit_alive": float(c[live].mean()) if live.any() else None,
            "share_of_team": float(share[..., cols].sum(-1)[mask].mean()),
        }
    steps = np.maximum(mask.sum(), 1)
    per_agent = [
        {
            "agent": i,
            "type": names[i],
            "mean_credit": float(c[..., i][mask].mean()),
            "mean_share": float(share[..., i][mask].mean()),
            "alive_fraction": float((alive[..., i] & mask).sum() / steps),
        }
        for i in range(n)
    ]
    return {
        "algo": cfg.algo_name,
        "env": cfg.env.id,
        "credit": _CREDIT[cfg.algo_name],
        "episodes": len(episodes),
        "win_rate": float(np.mean(won)),
        "groups": groups,
        "per_type": per_type,
        "per_agent": per_agent,
        "over_time": over_time,
        "per_episode": [
            _episode_record(k, ep, won[k], parts, alive) for k, ep in enumerate(episodes)
        ],
    }


_CREDIT = {
    "rdn": "LRP share of the critic's value (the agent's RDN target)",
    "vdn": "utility Q_i of the taken action (Q_tot is their sum)",
    "iql": "utility Q_i of the taken action",
    "qmix": "mixer gradient dQ_tot/dQ_i times the utility Q_i",
    "qmix_ns": "mixer gradient dQ_tot/dQ_i times the utility Q_i",
}


def _episode_record(k: int, ep: Episode, won: bool, parts: dict, alive: np.ndarray) -> dict:
    length = int(ep.filled.sum())
    rec = {"length": length, "won": bool(won), "return": float(ep.reward.sum())}
    for key in ("credit", "utility", "mixer_grad", "q_total"):
        if key in parts:
            rec[key] = np.round(parts[key][k, :length], 5).tolist()
    rec["alive"] = alive[k, :length].astype(int).tolist()
    return rec


def inspect(
    run: Path, out: Path, episodes: int = 8, member: int = 0, seed: int = 0,
    gif_episode: int = 0, max_frames: int = 150,
) -> dict:  # fmt: skip
    """Play, compute credit, write relevance.json / .png / .gif into `out`; returns the
    summary (without per-episode arrays)."""
    from cluster.core import write_json

    ckpt = find_checkpoint(run)
    cfg, learner = load_member(ckpt, member)
    eps, won, rec = play(cfg, learner, episodes, seed)
    parts = credit(cfg, learner, eps)
    b, t, n = parts["credit"].shape
    alive = np.zeros((b, t, n), bool)
    for k, frames in enumerate(rec.frames):
        for s in range(min(t, len(frames))):
            alive[k, s] = frames[s]["alive"][:n]
    names = list(rec.statics[0]["names"][:n])
    summary = summarise(cfg, names, parts, alive, eps, won)
    summary.update(checkpoint=str(ckpt), member=member, seed=seed)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "relevance.json", summary)
    plot(summary, out / "relevance.png")
    k = min(gif_episode, b - 1)
    write_gif(rec, k, parts["credit"][k], alive[k], summary, out / "relevance.gif", max_frames)
    return {key: v for key, v in summary.items() if key != "per_episode"}


def plot(summary: dict, path: Path) -> None:
    """Credit over time per (type, alive) group, each agent's mean credit, and each type's
    share of the team's credit."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.patches
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(17, 4.2))
    for key, ys in summary["over_time"].items():
        x = [i for i, y in enumerate(ys) if y is not None]
        axes[0].plot(x, [ys[i] for i in x], label=key, ls="-" if "alive" in key else ":")
    axes[0].set(xlabel="episode step", ylabel="mean credit per agent", title="credit over time")
    axes[0].legend(fontsize=7)
    agents = summary["per_agent"]
    kinds = sorted({a["type"] for a in agents})
    colors = {k: f"C{i}" for i, k in enumerate(kinds)}
    axes[1].bar(
        [a["agent"] for a in agents],
        [a["mean_credit"] for a in agents],
        color=[colors[a["type"]] for a in agents],
    )
    handles = [matplotlib.patches.Patch(color=colors[k], label=k) for k in kinds]
    axes[1].set(xlabel="agent", ylabel="mean credit over steps", title="credit per agent")
    axes[1].legend(handles=handles, fontsize=7)
    names = list(summary["per_type"])
    shares = [summary["per_type"][k]["share_of_team"] for k in names]
    labels = [f"{k} ({summary['per_type'][k]['agents']})" for k in names]
    axes[2].bar(labels, shares, color=[colors.get(k, "C0") for k in names])
    axes[2].set(ylabel="mean of Σ share over the type's agents", title="share of the team's credit")
    for ax in axes:
        ax.grid(alpha=0.3)
    won = summary["win_rate"]
    fig.suptitle(
        f"{summary['algo']} on {summary['env']}: {summary['credit']} "
        f"({summary['episodes']} greedy episodes, win rate {won:.2f})",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_gif(
    rec: Recorder,
    k: int,
    credit_k: np.ndarray,
    alive_k: np.ndarray,
    summary: dict,
    path: Path,
    max_frames: int,
) -> None:
    """Episode k as an animated GIF, each living agent tinted by its share of the credit at
    that step (green: positive, pink: negative; the brightest colour is the episode's
    largest |share|)."""
    import matplotlib

    from actors.envs.skirmish.render import draw_frame, write_images

    length = int(summary["per_episode"][k]["length"])
    denom = np.abs(credit_k[:length]).sum(-1, keepdims=True)
    share = np.where(denom > 0, credit_k[:length] / np.where(denom > 0, denom, 1.0), 0.0)
    top = float(np.abs(share).max()) or 1.0
    cmap = matplotlib.colormaps["PiYG"]
    frames = []
    for t, dyn in enumerate(rec.frames[k][: max_frames + 1]):
        tint = {}
        if t < length:
            tint = {i: cmap(0.5 + 0.5 * share[t, i] / top) for i in np.flatnonzero(alive_k[t])}
        title = f"{summary['algo']} {summary['env']}  t={t}"
        note = f"agents tinted by share of credit (green +, pink -; full colour = {top:.2f})"
        frames.append(draw_frame({**rec.statics[k], **dyn}, title, tint, note))
    write_images(frames, path)

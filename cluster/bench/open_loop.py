"""`credit bench open-loop`: open-loop policies on fixed vs randomised skirmish maps; prints
one JSON object (results/skirmish/README.md, "Open-loop policies").

    credit bench open-loop --maps 3m 2s3z protoss_5_vs_5 terran_5_vs_5 zerg_5_vs_5 \
        --tune-seeds 0 1 2 --out results/skirmish/open_loop.json

An open-loop policy sees only the time step, as in SMACv2's open-loop experiment: at step t
every agent prefers the action a[t] of one fixed sequence, then attacking enemy 0, 1, ...,
then stop, then the no-op, and takes the most preferred one the action mask allows (SMAC's
masked greedy choice). The sequence is a list of segments (move N/S/E/W, stop or attack
enemy j, each held for 1-11 steps). It is tuned on one seed: `--candidates` random sequences
are played on that seed's first `--tune-episodes` episodes, then `--rounds` rounds of as
many mutations of the best one (a stretch redrawn); the best has the most wins, then the
highest return. Then it is played on `--episodes` other seeds (1000 on). The
closed-loop focus-fire script on the same seeds is the reference. On a fixed map the seeds
change only the start jitter; on a randomised one (SMACv2-style) they change the unit types
and start positions.
"""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

import numpy as np

from actors.envs.registry import get_spec, make_vec_env
from actors.envs.skirmish.scripts import evaluate, focus_fire_policy
from cluster.bench.common import emit
from cluster.commands import add_command
from cluster.errors import UsageError

HELD_OUT_SEED = 1000


def random_sequence(rng: np.random.Generator, n_enemies: int, length: int) -> np.ndarray:
    """Segments of one action (30% a move, 10% stop, else attack enemy j) for 1-11 steps."""
    seq: list[int] = []
    while len(seq) < length:
        u = rng.random()
        if u < 0.3:
            a = int(rng.integers(2, 6))
        else:
            a = 1 if u < 0.4 else 6 + int(rng.integers(n_enemies))
        seq += [a] * int(rng.integers(1, 12))
    return np.array(seq[:length])


def mutate(seq: np.ndarray, rng: np.random.Generator, n_enemies: int) -> np.ndarray:
    """Redraw one stretch of `seq` (1-11 steps from a random start)."""
    out = seq.copy()
    start, n = int(rng.integers(len(seq))), int(rng.integers(1, 12))
    out[start : start + n] = random_sequence(rng, n_enemies, n)[: len(out[start : start + n])]
    return out


def tuning_starts(env_id: str, seed: int, episodes: int) -> list[np.random.Generator]:
    """The generators that start seed `seed`'s first `episodes` episodes (one each)."""
    venv = make_vec_env(env_id, 1, seed=seed)
    starts = []
    for _ in range(episodes):
        starts.append(copy.deepcopy(venv.rngs[0]))
        venv.reset()
    return starts


def play(env_id: str, seqs: np.ndarray, seed: int, starts: list | None = None) -> tuple:
    """Play each sequence of `seqs` [C, T] open-loop. With `starts` (K generators), each
    sequence plays those K episodes; else env k plays seed + k. Returns won and return [C, K]."""
    K = 1 if starts is None else len(starts)
    seqs = np.repeat(seqs, K, axis=0)
    M, T = seqs.shape
    venv = make_vec_env(env_id, M, seed=seed)
    if starts is not None:
        venv.rngs = [copy.deepcopy(starts[k % K]) for k in range(M)]
    venv.reset()
    A = venv.info.n_actions
    pref = np.zeros(A)
    pref[6:] = 10 - 1e-3 * np.arange(A - 6)  # attack enemy 0, 1, ... before stop, no-op
    pref[1], pref[0] = 1.0, 0.5
    active, won, ret, t = np.ones(M, bool), np.zeros(M, bool), np.zeros(M), 0
    while active.any():
        avail = venv.get_avail_actions()
        q = np.tile(pref, (M, 1))
        q[np.arange(M), seqs[:, min(t, T - 1)]] = 100.0
        acts = np.where(avail > 0, q[:, None, :], -1.0).argmax(-1)
        r, term, infos = venv.step(acts, active)
        ret += r
        for k in np.flatnonzero(term & active):
            won[k] = infos[k]["battle_won"]
        active &= ~term
        t += 1
    return won.reshape(-1, K), ret.reshape(-1, K)


def tune(env_id: str, seed: int, args: argparse.Namespace) -> tuple[np.ndarray, dict]:
    venv = make_vec_env(env_id, 1, seed=seed)
    E, T = venv.st.E, venv.spec.episode_limit
    rng = np.random.default_rng(seed)
    starts = tuning_starts(env_id, seed, args.tune_episodes)

    def score(seqs):
        won, ret = play(env_id, seqs, seed, starts)
        return won.sum(1) * 1000 + ret.mean(1), won.sum(1)

    seqs = np.stack([random_sequence(rng, E, T) for _ in range(args.candidates)])
    scores, wins = score(seqs)
    best = int(scores.argmax())
    seq, top, first_wins = seqs[best], scores[best], int(wins.max())
    for _ in range(args.rounds):
        kids = np.stack([mutate(seq, rng, E) for _ in range(args.candidates)])
        scores, _ = score(kids)
        k = int(scores.argmax())
        if scores[k] > top:
            seq, top = kids[k], scores[k]
    info = {"best_random_candidate_wins": first_wins, "tuned_wins": int(top // 1000),
            "tune_episodes": args.tune_episodes}  # fmt: skip
    return seq, info


def run_map(name: str, args: argparse.Namespace) -> dict:
    env_id = f"skirmish/{name}"
    rows = []
    for s in args.tune_seeds:
        seq, info = tune(env_id, s, args)
        held_won, held_ret = play(env_id, np.tile(seq, (args.episodes, 1)), HELD_OUT_SEED)
        rows.append({"tune_seed": s, **info, "open_loop_win_rate": float(held_won.mean()),
                     "open_loop_mean_return": float(held_ret.mean())})  # fmt: skip
    venv = make_vec_env(env_id, args.episodes, seed=HELD_OUT_SEED)
    closed = evaluate(venv, focus_fire_policy, args.episodes, seed=0)
    return {
        "map": name,
        "randomised": bool(venv.st.randomised),
        "open_loop_win_rate_mean": float(np.mean([r["open_loop_win_rate"] for r in rows])),
        "focus_fire_closed_loop_win_rate": closed["win_rate"],
        "per_tune_seed": rows,
    }


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "open-loop",
        "Tune open-loop action sequences on one seed of each skirmish map and play them on "
        "held-out seeds, beside the closed-loop focus-fire script; prints JSON, --out also "
        "writes it.",
    )
    p.add_argument("--maps", nargs="+", default=["3m", "2s3z", "protoss_5_vs_5"])
    p.add_argument("--tune-seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--candidates", type=int, default=200, help="sequences per round (200)")
    p.add_argument("--tune-episodes", type=int, default=8, help="episodes of the tuning seed (8)")
    p.add_argument("--rounds", type=int, default=3, help="rounds of mutations of the best (3)")
    p.add_argument("--episodes", type=int, default=200, help="held-out episodes per sequence")
    p.add_argument("--out", default=None, help="also write the JSON here")
    p.set_defaults(func=cmd_open_loop)


def cmd_open_loop(args: argparse.Namespace) -> int:
    for name in ("candidates", "tune_episodes", "episodes"):
        if getattr(args, name) < 1:
            raise UsageError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.rounds < 0:
        raise UsageError(f"--rounds must be >= 0, got {args.rounds}")
    for m in args.maps:
        get_spec(f"skirmish/{m}")  # an unknown map stops the run before any map is played
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    maps = [run_map(m, args) for m in args.maps]
    figures = {
        "seconds": round(time.time() - t0, 1),
        "held_out_seeds": [HELD_OUT_SEED, HELD_OUT_SEED + args.episodes - 1],
        "maps": maps,
    }
    emit("open_loop", figures, args.out)
    return 0

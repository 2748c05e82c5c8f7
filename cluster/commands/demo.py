"""`credit demo`: the main job on the embedded default, small enough to watch.

Trains RDN on the four-game matrix game in one process, then reproduces the seed's Fig. 5.3
for every algorithm on that game (8 seeds each, seed-batched) and prints where it all is.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from cluster.commands import repro, train

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="train RDN on the four-game, then the reproduction plot")
    p.add_argument("--out", default="runs/demo", help="output folder (default runs/demo)")
    p.add_argument("--seeds", type=int, default=8, help="seeds per algorithm in the reproduction")
    p.set_defaults(func=cmd_demo)


def cmd_demo(args: argparse.Namespace) -> int:
    out = Path(args.out)
    run_dir = out / "rdn_four_game"
    log.info("1/2 training RDN on matrix/four_game -> %s", run_dir)
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    train.register(sub)
    repro.register(sub)
    code = train.cmd_train(
        parser.parse_args(
            ["train", "--algo", "rdn", "--env", "matrix/four_game", "--out", str(run_dir)]
        )
    )
    if code:
        return code
    repro_dir = out / "repro_matrix"
    log.info(
        "2/2 reproducing seed Fig. 5.3 on matrix/four_game (%d seeds per algorithm) -> %s",
        args.seeds,
        repro_dir,
    )
    repro_args = [
        "repro",
        "matrix",
        "--seeds",
        str(args.seeds),
        "--games",
        "matrix/four_game",
        "--out",
        str(repro_dir),
    ]
    code = repro.cmd_matrix(parser.parse_args(repro_args))
    if code:
        return code
    print(f"\ndemo finished; results under {out}/:")
    print(f"  {run_dir}/summary.json, metrics.jsonl, checkpoint/  (RDN training run)")
    band = f"median and 25-75% band over {args.seeds} seeds"
    print(f"  {repro_dir}/summary.json, matrix_four_game.png  ({band})")
    print("the full experiment on both games: credit repro matrix --seeds 8 --out results/matrix")
    return 0

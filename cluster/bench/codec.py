"""`credit bench codec`: wire codec throughput against a plain memcpy of the same bytes.

The payload is one sample reply of a bane_vs_bane-sized batch (N=24 agents, obs 336, state
984, 30 actions, T=200, batch 32, about 240 MB of arrays; random, so dense: packed as the
buffer stores them, `buffer_service.packed`, they take about as much). Encoding packs the
reply frame
(msgpack bin straight from each array's memory); decoding unpacks it and wraps every
array with np.frombuffer. memcpy copies the same number of bytes between two preallocated
buffers (``memcpy_gb_per_s``; ``memcpy_fresh_buffer_gb_per_s`` copies into a newly
allocated buffer, as `encode` must). ``encode_parts`` is the scatter list the server hands
the socket (large arrays referenced, not copied). All run in the same process,
interleaved, best of `--repeats`.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from buffer_service import codec
from buffer_service.episode import Episode, EpisodeSchema
from buffer_service.packed import PackedEpisode
from cluster.bench.common import emit
from cluster.commands import add_command

BANE = EpisodeSchema(n_agents=24, obs_dim=336, state_dim=984, n_actions=30, max_t=200)


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "codec",
        "Time the msgpack episode codec against memcpy and print GB/s as JSON; --out also"
        " writes that JSON to a file.",
    )
    p.add_argument("--batch", type=int, default=32, help="episodes per frame")
    p.add_argument("--t", type=int, default=200, help="transitions per episode")
    p.add_argument("--repeats", type=int, default=5, help="timed repetitions (best is kept)")
    p.add_argument("--out", help="also write the JSON here")
    p.set_defaults(func=cmd_codec)


def bane_episode(seq: int, t: int, rng: np.random.Generator) -> Episode:
    s = BANE
    return Episode(
        obs=rng.random((t + 1, s.n_agents, s.obs_dim), dtype=np.float32),
        state=rng.random((t + 1, s.state_dim), dtype=np.float32),
        avail_actions=np.ones((t + 1, s.n_agents, s.n_actions), np.uint8),
        actions=rng.integers(0, s.n_actions, (t, s.n_agents)),
        reward=rng.random(t, dtype=np.float32),
        terminated=np.zeros(t, bool),
        filled=np.ones(t, bool),
        actor_id=0,
        episode_seq=seq,
    )


def _best(fn, repeats: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def run(batch: int, t: int, repeats: int) -> dict:
    rng = np.random.default_rng(0)
    eps = [bane_episode(i, t, rng) for i in range(batch)]
    stored = [PackedEpisode.pack(ep) for ep in eps]  # what the server holds and sends
    nbytes = sum(p.data.nbytes for p in stored)

    def reply() -> dict:
        return {"ok": True, "v": 2, "episodes": [codec.episode_to_wire(p) for p in stored]}

    def encode() -> np.ndarray:  # one contiguous frame body: every array byte copied once
        return codec.pack_contiguous(reply())

    def encode_parts() -> list:  # what the server hands the socket: references, no copy
        return codec.pack_parts(reply())

    body = codec.pack(reply())
    assert encode().tobytes() == body

    def decode() -> list[PackedEpisode]:
        return [codec.episode_from_wire(w) for w in codec.unpack(body)["episodes"]]

    src = np.frombuffer(body, np.uint8)[:nbytes]
    dst = np.empty_like(src)
    enc_s = dec_s = cpy_s = parts_s = fresh_s = float("inf")
    for _ in range(repeats):  # interleaved so drift on a shared machine hits all of them
        enc_s = min(enc_s, _best(encode, 1)[0])
        parts_s = min(parts_s, _best(encode_parts, 1)[0])
        dec_s = min(dec_s, _best(decode, 1)[0])
        cpy_s = min(cpy_s, _best(lambda: np.copyto(dst, src), 1)[0])
        fresh_s = min(fresh_s, _best(src.copy, 1)[0])
    back = decode()
    assert all(np.array_equal(a.obs, b.obs) for a, b in zip(eps, back, strict=True))
    gb = nbytes / 1e9
    enc, dec, cpy = gb / enc_s, gb / dec_s, gb / cpy_s
    return {
        "payload": {"schema": BANE.to_dict(), "batch": batch, "t": t},
        "array_bytes": nbytes,
        "frame_bytes": len(body),
        "repeats": repeats,
        "encode_gb_per_s": round(enc, 3),
        "decode_gb_per_s": round(dec, 3),
        "memcpy_gb_per_s": round(cpy, 3),
        "memcpy_fresh_buffer_gb_per_s": round(gb / fresh_s, 3),
        "encode_parts_gb_per_s": round(gb / parts_s, 3),
        "encode_vs_memcpy": round(enc / cpy, 3),
        "decode_vs_memcpy": round(dec / cpy, 3),
        "memcpy_over_encode": round(cpy / enc, 3),
        "memcpy_over_decode": round(cpy / dec, 3),
    }


def cmd_codec(args: argparse.Namespace) -> int:
    emit("codec", run(args.batch, args.t, args.repeats), out=args.out)
    return 0

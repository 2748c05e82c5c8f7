"""Episodes as the buffer stores them: an exact, compact encoding of `Episode` (issue 35).

`PackedEpisode` holds one episode in a single byte buffer; decoding it gives back the very
bits `Episode` held (float32 values are copied bit for bit, -0.0 and all), so a batch made
from packed episodes is bit-identical to one made from the originals and learning cannot
change. On skirmish/bane_vs_bane it takes about a twelfth of `Episode`'s bytes per env step
(`credit bench memory`), because SMAC-style observations are mostly zero (dead or unseen
units) and half of their non-zero entries are exactly 1.0 (flags and one-hots).

A float array [M rows, F features] (obs: rows are (step, agent); state: rows are steps) is
stored as, in this order of the buffer's sections:

* ``values``: float32, its non-zero entries that are not exactly 1.0, row-major order;
* ``live``: one bit per row, set when the row has a non-zero entry (numpy packbits order);
* ``nonzero``: for the live rows only, one bit per entry: non-zero (bitwise: -0.0 counts);
* ``ones``: one bit per non-zero entry: exactly 1.0 (its value is then not stored).

The episode's buffer (format `PACKING`, recorded on the wire): obs values, state values,
reward (float32 [T]), then actions ([T, N], uint8 when A <= 256, else int32), then the bit
sections of obs and state, then avail_actions bit-packed ([T+1, N, A], values 0 or 1).
``terminated`` is one flag (only the last transition may be terminal), ``filled`` is all
true in a stored episode and is not stored. An episode stored without the state (state_dim
0: the learner never reads it, `learner.registry.AlgoSpec.reads_state`) decodes to a state
of shape [T+1, 0].
"""

from __future__ import annotations

import mmap
from dataclasses import dataclass, replace
from itertools import accumulate

import numpy as np

from buffer_service.episode import (
    EPISODE_ARRAYS,
    EPISODE_DTYPES,
    Episode,
    EpisodeError,
    EpisodeSchema,
    off_heap_array,
)

PACKING = 1  # the layout version written by `PackedEpisode.pack`; the wire records it
# The Python objects of one stored episode, counted into `nbytes`: the dataclass, its array's
# header, its counts, and the buffer's bookkeeping (dicts of keys, refs, dedup); tracemalloc
# measured 868 bytes an episode over 2,000 inserted into a BufferState.
OVERHEAD_BYTES = 900


MAPPED_MIN_BYTES = 64 * 2**10  # buffers at least this large get their own mapping


def stored_buffer(nbytes: int) -> np.ndarray:
    """A uint8 buffer for one stored episode, outside malloc's heap when it is large.

    Stored episodes live long and are freed in FIFO order, while the learner allocates and
    frees blocks of tens of MiB on every update. From one heap (with `run.keep_freed_memory`
    every block comes from it and it is never trimmed) the episodes pin the heap's holes, so
    the update's blocks keep needing fresh memory on top and the process grows by more than
    the stored bytes (measured: `cluster.alloc`). A buffer of its own (an anonymous mmap,
    unmapped when the last view of it goes) keeps the replay out of the heap: resident
    memory is the heap's peak plus the stored bytes (rounded up to pages). Small buffers
    (3m's episodes) stay on the heap, where a page each would waste more than fragmentation
    costs.
    """
    return off_heap_array((nbytes,), np.uint8, MAPPED_MIN_BYTES, zeroed=False)  # all written


def joined(parts: list[np.ndarray]) -> np.ndarray:
    """`parts` (flat uint8) concatenated into one `stored_buffer`."""
    out = stored_buffer(sum(p.size for p in parts))
    pos = 0
    for p in parts:
        out[pos : pos + p.size] = p
        pos += p.size
    return out


def _bits(n: int) -> int:
    """Bytes of `n` packed bits."""
    return (n + 7) // 8


@dataclass(frozen=True)
class FloatCounts:
    """Sizes of one packed float array: rows M, features F, live rows L, non-zeros K,
    stored values V (K minus the entries that are exactly 1.0)."""

    rows: int
    features: int
    live: int
    nonzero: int
    values: int

    @property
    def flagged_rows(self) -> int:
        """Rows with a live bit: all of them, none when there are no features (no state)."""
        return self.rows if self.features else 0

    def bit_bytes(self) -> tuple[int, int, int]:
        """Bytes of the live, nonzero and ones sections."""
        return _bits(self.flagged_rows), _bits(self.live * self.features), _bits(self.nonzero)

    def check(self, name: str) -> None:
        if not (
            0 <= self.live <= self.rows
            and 0 <= self.nonzero <= self.live * self.features
            and 0 <= self.values <= self.nonzero
            and self.live <= self.nonzero
        ):
            raise EpisodeError(f"packed {name}: inconsistent counts {self}")


def _uint32_rows(a: np.ndarray) -> np.ndarray:
    """float rows `a` [M, F] as contiguous uint32 bits (a view when already float32)."""
    return np.ascontiguousarray(a, np.float32).view(np.uint32)


def _sizes(t: int, dims: tuple[int, int, int, int], oc: FloatCounts, sc: FloatCounts):
    """The byte sizes of the `SECTIONS` (Python ints: counts from the wire may ask for more
    than int64 holds, which `check_layout` refuses by comparing their sum with the buffer)."""
    n, a = dims[0], dims[3]
    return (
        4 * oc.values,
        4 * sc.values,
        4 * t,
        (1 if a <= 256 else 4) * t * n,
        *oc.bit_bytes(),
        *sc.bit_bytes(),
        _bits((t + 1) * n * a),
    )


def _offsets(t: int, dims: tuple[int, int, int, int], oc: FloatCounts, sc: FloatCounts):
    """The start offsets of the `SECTIONS`, then the buffer's end (the kernels' form of a
    layout)."""
    return _starts(_sizes(t, dims, oc, sc))


def _starts(sizes: tuple[int, ...]) -> np.ndarray:
    """Section sizes -> their start offsets, then the end (int64)."""
    return np.fromiter(accumulate(sizes, initial=0), np.int64, len(sizes) + 1)


SECTIONS = (
    "obs_values",
    "state_values",
    "reward",
    "actions",
    "obs_live",
    "obs_nonzero",
    "obs_ones",
    "state_live",
    "state_nonzero",
    "state_ones",
    "avail",
)


def section_layout(
    t: int, dims: tuple[int, int, int, int], oc: FloatCounts, sc: FloatCounts
) -> dict[str, tuple[int, int]]:
    """name -> (offset, bytes) of every section of a packed episode's buffer."""
    off = _offsets(t, dims, oc, sc).tolist()
    return {name: (off[i], off[i + 1] - off[i]) for i, name in enumerate(SECTIONS)}


@dataclass(frozen=True)
class PackedEpisode:
    """One episode in its stored form (see the module docstring for the layout).

    Attributes:
        length: T transitions.
        dims: (N agents, O obs, S state (0: not stored), A actions).
        obs_counts, state_counts: sizes of the packed obs [(T+1) * N, O] and state [T+1, S].
        terminated_last: whether the last transition is a true termination.
        data: the buffer (uint8), which owns its bytes unless it views a received frame.
        actor_id, episode_seq, policy_version: as `Episode`'s.

    The dense fields of `Episode` (obs, state, avail_actions, actions, reward, terminated,
    filled) are properties that decode on every access: tests and tools read them; making a
    batch decodes straight into the batch's arrays instead (`write_into`).
    """

    length: int
    dims: tuple[int, int, int, int]
    obs_counts: FloatCounts
    state_counts: FloatCounts
    terminated_last: bool
    data: np.ndarray
    actor_id: int = 0
    episode_seq: int = 0
    policy_version: int = 0

    # -- layout ---------------------------------------------------------------------------
    @property
    def action_dtype(self) -> np.dtype:
        return np.dtype(np.uint8) if self.dims[3] <= 256 else np.dtype("<i4")

    @property
    def layout(self) -> dict[str, tuple[int, int]]:
        """name -> (offset, bytes) of every section of `data` (computed on each call: a
        cached copy would cost every stored episode a kilobyte)."""
        return section_layout(self.length, self.dims, self.obs_counts, self.state_counts)

    @property
    def offsets(self) -> np.ndarray:
        """The start offsets of the `SECTIONS` in `data`, then its end (the kernels' form)."""
        return _offsets(self.length, self.dims, self.obs_counts, self.state_counts)

    def _view(self, name: str, dtype=np.uint8, layout: dict | None = None) -> np.ndarray:
        off, size = (layout or self.layout)[name]
        return self.data[off : off + size].view(dtype)

    @property
    def key(self) -> tuple[int, int]:
        return (int(self.actor_id), int(self.episode_seq))

    @property
    def has_state(self) -> bool:
        return self.dims[2] > 0

    @property
    def nbytes(self) -> int:
        """What storing this episode costs: its buffer plus the Python objects around it."""
        size = int(self.data.nbytes)
        if size >= MAPPED_MIN_BYTES:  # its own mapping: whole pages
            size = -(-size // mmap.PAGESIZE) * mmap.PAGESIZE
        return size + OVERHEAD_BYTES

    # -- packing --------------------------------------------------------------------------
    @classmethod
    def pack(cls, ep: Episode | PackedEpisode, state: bool = True) -> PackedEpisode:
        """`ep` packed (a packed one is returned as it is, or without its state).

        Args:
            ep: the episode; its arrays must have the shapes `Episode` documents,
                avail_actions only 0 and 1, terminated only at the end and filled all true
                (EpisodeError otherwise: the packed form cannot hold anything else).
            state: keep the state (False: the learner never reads it).
        """
        if isinstance(ep, PackedEpisode):
            return ep if state or not ep.has_state else ep.without_state()
        from buffer_service import pack_kernels as kernels  # numba: only where episodes are packed

        t, (n, o, s, a) = ep.length, kernels.episode_dims(ep)
        obs, st = ep.obs, ep.state if state else ep.state[:, :0]
        s = s if state else 0
        avail = ep.avail_actions
        if avail.dtype not in (np.uint8, np.bool_) and np.any((avail < 0) | (avail > 1)):
            raise EpisodeError(kernels.ERRORS[kernels.BAD_AVAIL])  # before a cast could wrap
        obits = _uint32_rows(obs.reshape(-1, o))
        sbits = _uint32_rows(st)
        lo, zo, vo, ls, zs, vs = kernels.counts(obits, sbits)
        oc, sc = FloatCounts(obits.shape[0], o, lo, zo, vo), FloatCounts(t + 1, s, ls, zs, vs)
        offsets = _offsets(t, (n, o, s, a), oc, sc)
        data = stored_buffer(int(offsets[-1]))
        code = kernels.fill(
            obits,
            sbits,
            np.ascontiguousarray(ep.reward, np.float32).reshape(-1),
            np.ascontiguousarray(ep.actions, np.int64).reshape(-1),
            np.ascontiguousarray(avail, np.uint8).reshape(-1),
            np.ascontiguousarray(ep.terminated, np.bool_).reshape(-1),
            np.ascontiguousarray(ep.filled, np.bool_).reshape(-1),
            a,
            data,
            offsets,
        )
        if code != kernels.OK:
            raise EpisodeError(kernels.ERRORS[code].format(a - 1))
        return cls(
            length=t,
            dims=(n, o, s, a),
            obs_counts=oc,
            state_counts=sc,
            terminated_last=bool(ep.terminated[-1]),
            data=data,
            actor_id=int(ep.actor_id),
            episode_seq=int(ep.episode_seq),
            policy_version=int(ep.policy_version),
        )

    def without_state(self) -> PackedEpisode:
        """This episode with its state dropped (a copy of the rest of the buffer)."""
        lay = self.layout
        data = joined([self._view(k, layout=lay) for k in lay if not k.startswith("state")])
        n, o, _, a = self.dims
        empty = FloatCounts(self.length + 1, 0, 0, 0, 0)
        return replace(self, dims=(n, o, 0, a), state_counts=empty, data=data)

    def owned(self) -> PackedEpisode:
        """A copy whose buffer owns its bytes (not a view of a received frame)."""
        return replace(self, data=joined([self.data]))

    # -- checks ---------------------------------------------------------------------------
    def check_layout(self) -> None:
        """EpisodeError unless the counts agree with the buffer and its bit sections."""
        t, (n, o, s, a) = self.length, self.dims
        if t < 1 or min(n, o, a) < 1 or s < 0:
            raise EpisodeError(f"packed episode: length {t} or dims {self.dims} out of range")
        oc, sc = self.obs_counts, self.state_counts
        if (oc.rows, oc.features) != ((t + 1) * n, o) or (sc.rows, sc.features) != (t + 1, s):
            raise EpisodeError(f"packed episode: counts {oc} / {sc} do not fit dims {self.dims}")
        oc.check("obs")
        sc.check("state")
        if self.data.dtype != np.uint8 or self.data.ndim != 1:
            raise EpisodeError("packed episode: data must be a flat uint8 array")
        from buffer_service import pack_kernels as kernels  # numba: only where checked

        sizes = _sizes(t, self.dims, oc, sc)
        if self.data.size != sum(sizes):
            raise EpisodeError(
                f"packed episode: data holds {self.data.size} bytes, its counts need {sum(sizes)}"
            )
        offsets = _starts(sizes)  # (only now: the sum fits int64, as the buffer's size does)
        # the six bit sections: set bits and padding against the counts, in one compiled pass
        expect = np.array(self._bit_counts(oc) + self._bit_counts(sc), np.int64)
        bad = kernels.check_bits(self.data, offsets, expect)
        if bad == -2:
            raise EpisodeError("packed episode: its sections pass the end of its buffer")
        if bad != -1:
            prefix, part = SECTIONS[4 + bad].split("_")
            raise EpisodeError(f"packed {prefix}: {part} bits disagree with its counts")

    @staticmethod
    def _bit_counts(c: FloatCounts) -> list[tuple[int, int]]:
        """(bits set, bits used) of the live, nonzero and ones sections."""
        return [
            (c.live, c.flagged_rows),
            (c.nonzero, c.live * c.features),
            (c.nonzero - c.values, c.nonzero),
        ]

    def validate(self, schema: EpisodeSchema) -> None:
        """Raise EpisodeError naming the first thing that breaks `schema` (the layout, then
        every check of `Episode.validate`, made on the packed sections)."""
        self.check_layout()
        self.validate_contents(schema)

    def validate_contents(self, schema: EpisodeSchema) -> None:
        """`validate` without the layout check, for an episode whose layout is checked
        already (`codec.episode_from_wire` checks every episode it decodes)."""
        n, o, s, a = self.dims
        want = (schema.n_agents, schema.obs_dim, schema.n_actions)
        if (n, o, a) != want or s not in (0, schema.state_dim):
            raise EpisodeError(
                f"packed episode has shape (agents, obs, state, actions) {self.dims}, the "
                f"schema {(schema.n_agents, schema.obs_dim, schema.state_dim, schema.n_actions)}"
                " (state 0 allowed)"
            )
        self._validate_values(schema)

    def _validate_values(self, schema: EpisodeSchema) -> None:
        """`Episode.validate`'s checks of the values, made on the packed sections (the same
        errors, in the same order; zeros and the 1.0 entries are finite, avail_actions is
        bit-packed so only 0 and 1, filled and terminated cannot be wrong)."""
        from buffer_service import pack_kernels as kernels  # numba: only where checked

        t, (n, _, _, a) = self.length, self.dims
        if not 1 <= t <= schema.max_t:
            raise EpisodeError(f"episode length {t} outside 1..{schema.max_t}")
        code, row = kernels.check_values(self.data, self.offsets, t, n, a, schema.n_actions)
        if code == kernels.OUT_OF_BOUNDS:
            raise EpisodeError("packed episode: its sections pass the end of its buffer")
        if code in kernels.NONFINITE_FIELDS:
            raise EpisodeError(f"field {kernels.NONFINITE_FIELDS[code]!r} holds NaN or inf")
        if code == kernels.ACTION_RANGE:
            raise EpisodeError(f"field 'actions' has values outside 0..{schema.n_actions - 1}")
        if code == kernels.AVAIL_STUCK:
            raise EpisodeError(
                f"field 'avail_actions': agent {row % n} has no available action at step {row // n}"
            )

    # -- decoding -------------------------------------------------------------------------
    def write_into(self, out: dict[str, np.ndarray], i: int) -> None:
        """Decode into row `i` of a batch's zero-filled arrays (obs [B, T'+1, N, O], ...)."""
        from buffer_service import pack_kernels as kernels  # numba: only where decoded

        t, (_, o, s, a) = self.length, self.dims
        ok = kernels.decode(
            self.data,
            _offsets(t, self.dims, self.obs_counts, self.state_counts),
            out["obs"][i, : t + 1].reshape(-1, o).view(np.uint32),
            out["state"][i, : t + 1, :s].view(np.uint32),
            out["reward"][i, :t],
            out["actions"][i, :t].reshape(-1),
            out["avail_actions"][i, : t + 1].reshape(-1),
            a > 256,
        )
        if not ok:
            raise EpisodeError(f"packed episode {self.key}: its bits disagree with its counts")
        out["terminated"][i, t - 1] = self.terminated_last
        out["filled"][i, :t] = True

    def unpack(self) -> Episode:
        """The `Episode` this was packed from (the state [T+1, 0] when it was dropped)."""
        t, (n, o, s, a) = self.length, self.dims
        shapes = EpisodeSchema(n, o, max(s, 1), a, t).shapes(t)
        shapes["state"] = (t + 1, s)
        out = {k: np.zeros((1, *shape), EPISODE_DTYPES[k]) for k, shape in shapes.items()}
        self.write_into(out, 0)
        arrays = {k: v[0] for k, v in out.items()}
        return Episode(**arrays, **self.scalars())

    def scalars(self) -> dict[str, int]:
        return {
            "actor_id": self.actor_id,
            "episode_seq": self.episode_seq,
            "policy_version": self.policy_version,
        }

    obs = property(lambda self: self.unpack().obs)
    state = property(lambda self: self.unpack().state)
    avail_actions = property(lambda self: self.unpack().avail_actions)
    actions = property(lambda self: self.unpack().actions)
    reward = property(lambda self: self.unpack().reward)
    terminated = property(lambda self: self.unpack().terminated)
    filled = property(lambda self: np.ones(self.length, np.bool_))


def dense_bytes(ep: Episode) -> int:
    """Bytes of `ep`'s arrays (today's `Episode`, the old layout)."""
    return sum(int(getattr(ep, f).nbytes) for f in EPISODE_ARRAYS)


def warm_kernels() -> None:
    """Load the kernels the buffer service calls, with the argument types it passes them.

    A process's first kernel call loads numba and its compiled code (about 0.8 s on the
    2-core machine, from numba's cache; a compile on a machine's first run). The service
    checks every packed insert with `check_bits` and `check_values`, on arrays that view the
    received frame (read-only) or own their bytes; it calls this before it listens, so that
    its first insert does not wait. (Dense protocol-1 inserts, packed by the server from
    read-only arrays, still load `counts` and `fill` for those types on first use.)
    """
    t, n, o, s, a = 1, 1, 1, 1, 2
    ep = Episode(
        obs=np.ones((t + 1, n, o), np.float32),
        state=np.ones((t + 1, s), np.float32),
        avail_actions=np.ones((t + 1, n, a), np.uint8),
        actions=np.zeros((t, n), np.int64),
        reward=np.zeros(t, np.float32),
        terminated=np.zeros(t, bool),
        filled=np.ones(t, bool),
    )
    packed = PackedEpisode.pack(ep)
    framed = replace(packed, data=np.frombuffer(packed.data.tobytes(), np.uint8))  # read-only
    for p in (packed, framed):
        p.validate(EpisodeSchema(n, o, s, a, t))

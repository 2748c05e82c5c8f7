"""Numba kernels that write an episode into `buffer_service.packed`'s layout and read it back.

`PackedEpisode.pack` runs once per episode in every actor (and in the service benchmark's
client threads, which share one interpreter lock). Built from numpy calls, the encoding took
about forty calls and their temporaries per episode, and for small episodes (3m: 5,490
observation values) the cost was the calls themselves. Here it is two compiled calls that
release the lock: one counts what the float arrays hold, the other checks the episode and
writes every section straight into its buffer. They produce the same bytes as the numpy
encoding they replace; `tests/buffer_service/test_packed.py` checks that against a numpy
reference. `decode` reads an episode straight into a batch's arrays (one call per episode,
where numpy took about fifteen; the batch is bit-identical to one made from the dense
episodes, which the same tests check). `check_bits` and `check_values` are the server's checks
of an inserted episode (`PackedEpisode.check_layout` and `validate_contents`) in two compiled
passes, where the numpy checks took about thirty calls (44 µs of CPU per 3m-sized insert,
about 21 µs now); the same tests compare them with those numpy checks on corrupted buffers.

Bit sections use numpy's packbits order (the first bit is a byte's most significant).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from buffer_service.episode import EPISODE_ARRAYS, Episode, EpisodeError

ONE_BITS = np.uint32(np.float32(1.0).view(np.uint32))
# fill()'s return codes
OK, BAD_AVAIL, EARLY_TERMINATED, NOT_FILLED, BAD_ACTION = 0, 1, 2, 3, 4


def episode_dims(ep: Episode) -> tuple[int, int, int, int]:
    """(N, O, S, A) of `ep`, after checking that its arrays' shapes agree with each other
    (the kernels index by them; an episode from the wire may say anything)."""
    arrays = {name: getattr(ep, name) for name in EPISODE_ARRAYS}
    for name, arr in arrays.items():
        if not isinstance(arr, np.ndarray):
            raise EpisodeError(f"field {name!r} is {type(arr).__name__}, not a numpy array")
    axes = {"obs": 3, "state": 2, "avail_actions": 3, "actions": 2}
    for name, k in axes.items():
        if arrays[name].ndim != k:
            raise EpisodeError(f"field {name!r} has shape {arrays[name].shape}: needs {k} axes")
    t, (n, o), s, a = (
        ep.actions.shape[0],
        ep.obs.shape[1:],
        ep.state.shape[1],
        ep.avail_actions.shape[2],
    )
    shapes = {
        "obs": (t + 1, n, o),
        "state": (t + 1, s),
        "avail_actions": (t + 1, n, a),
        "actions": (t, n),
        "reward": (t,),
        "terminated": (t,),
        "filled": (t,),
    }
    for name, shape in shapes.items():
        if arrays[name].shape != shape:
            raise EpisodeError(f"field {name!r} has shape {arrays[name].shape}, expected {shape}")
    if t < 1 or min(n, o, a) < 1:
        raise EpisodeError(f"episode of length {t} with dims {(n, o, s, a)} cannot be packed")
    return n, o, s, a


ERRORS = {
    BAD_AVAIL: "field 'avail_actions' holds values other than 0 and 1",
    EARLY_TERMINATED: "field 'terminated' is set before the last transition",
    NOT_FILLED: "field 'filled' must be all true in a stored episode",
    BAD_ACTION: "field 'actions' has values outside 0..{}",
}


@njit(cache=True, nogil=True)
def _float_counts(bits: np.ndarray) -> tuple[int, int, int]:
    live = 0
    nonzero = 0
    ones = 0
    for i in range(bits.shape[0]):
        row = 0
        for j in range(bits.shape[1]):
            b = bits[i, j]
            if b != 0:
                row += 1
                if b == ONE_BITS:
                    ones += 1
        if row:
            live += 1
            nonzero += row
    return live, nonzero, nonzero - ones


@njit(cache=True, nogil=True)
def counts(obs: np.ndarray, state: np.ndarray) -> tuple[int, int, int, int, int, int]:
    """(live rows, non-zero entries, stored values) of the uint32 rows `obs` [M, O], then
    of `state` [T+1, S]: entries are non-zero bitwise (-0.0 counts), and stored values
    exclude the entries exactly 1.0."""
    lo, zo, vo = _float_counts(obs)
    ls, zs, vs = _float_counts(state)
    return lo, zo, vo, ls, zs, vs


@njit(cache=True, nogil=True)
def _set_bit(out: np.ndarray, off: int, i: int) -> None:
    out[off + (i >> 3)] |= np.uint8(0x80 >> (i & 7))


@njit(cache=True, nogil=True)
def _push(data: np.ndarray, acc: int, n: int, pos: int, bit: bool) -> tuple[int, int, int]:
    """Append `bit` to the byte gathered in `acc` (n bits so far), writing it at `pos` when
    full; returns the new (acc, n, pos)."""
    acc = (acc << 1) | bit
    n += 1
    if n == 8:
        data[pos] = acc
        return 0, 0, pos + 1
    return acc, n, pos


@njit(cache=True, nogil=True)
def _encode(bits: np.ndarray, vals: np.ndarray, data: np.ndarray, live: int, nz: int, ones: int):
    """Write uint32 rows `bits` [M, F]: the stored values' bits into `vals` (uint32), and
    into `data` at its bit sections' byte offsets a live bit per row (when F > 0), a bit per
    entry of a live row and a bit per non-zero entry (the live section must be zeroed)."""
    v = 0
    nz_acc, nz_n, nz_pos = 0, 0, nz
    one_acc, one_n, one_pos = 0, 0, ones
    for i in range(bits.shape[0]):
        alive = False
        for j in range(bits.shape[1]):
            if bits[i, j] != 0:
                alive = True
                break
        if not alive:
            continue
        _set_bit(data, live, i)
        for j in range(bits.shape[1]):
            b = bits[i, j]
            nz_acc, nz_n, nz_pos = _push(data, nz_acc, nz_n, nz_pos, b != 0)
            if b != 0:
                one_acc, one_n, one_pos = _push(data, one_acc, one_n, one_pos, b == ONE_BITS)
                if b != ONE_BITS:
                    vals[v] = b
                    v += 1
    if nz_n:
        data[nz_pos] = nz_acc << (8 - nz_n)
    if one_n:
        data[one_pos] = one_acc << (8 - one_n)


@njit(cache=True, nogil=True)
def fill(
    obs: np.ndarray,
    state: np.ndarray,
    reward: np.ndarray,
    actions: np.ndarray,
    avail: np.ndarray,
    terminated: np.ndarray,
    filled: np.ndarray,
    n_actions: int,
    data: np.ndarray,
    offsets: np.ndarray,
) -> int:
    """Check the episode, then write it into `data` (uint8) at `offsets` (int64: obs
    values, state values, reward, actions, obs live/nonzero/ones, state live/nonzero/ones,
    avail, end). Returns OK, or the first failed check's code with nothing written.

    reward: float32 [T]; actions: int64 [T*N]; avail, terminated, filled: flat uint8/bool.
    """
    for i in range(avail.size):
        if avail[i] > 1:
            return BAD_AVAIL
    for i in range(terminated.size - 1):
        if terminated[i]:
            return EARLY_TERMINATED
    for i in range(filled.size):
        if not filled[i]:
            return NOT_FILLED
    for i in range(actions.size):
        if actions[i] < 0 or actions[i] >= n_actions:
            return BAD_ACTION
    data[offsets[4] : offsets[11]] = 0  # every bit section, avail included
    obs_vals = data[offsets[0] : offsets[1]].view(np.uint32)
    state_vals = data[offsets[1] : offsets[2]].view(np.uint32)
    _encode(obs, obs_vals, data, offsets[4], offsets[5], offsets[6])
    _encode(state, state_vals, data, offsets[7], offsets[8], offsets[9])
    data[offsets[2] : offsets[3]].view(np.float32)[:] = reward
    if n_actions > 256:
        data[offsets[3] : offsets[4]].view(np.int32)[:] = actions
    else:
        data[offsets[3] : offsets[4]][:] = actions
    for i in range(avail.size):
        if avail[i]:
            _set_bit(data, offsets[10], i)
    return OK


@njit(cache=True, nogil=True)
def _bit(data: np.ndarray, off: int, i: int) -> bool:
    return (data[off + (i >> 3)] >> (7 - (i & 7))) & 1 == 1


@njit(cache=True, nogil=True)
def _decode(data: np.ndarray, vals: np.ndarray, sections: np.ndarray, out: np.ndarray) -> bool:
    """Write packed rows into `out` (uint32 [M, F], zero-filled) from `vals` and the bit
    sections at byte offsets `sections` (live, nonzero, ones, end; contiguous). False when
    the bits ask for more values or bits than the buffer holds (a corrupt episode)."""
    live, nz, ones, end = sections[0], sections[1], sections[2], sections[3]
    v = 0
    k = 0
    z = 0
    for i in range(out.shape[0]):
        if out.shape[1] == 0:
            break
        if (i >> 3) >= nz - live:
            return False
        if not _bit(data, live, i):
            continue
        for j in range(out.shape[1]):
            if (k >> 3) >= ones - nz:
                return False
            if _bit(data, nz, k):
                if (z >> 3) >= end - ones:
                    return False
                if _bit(data, ones, z):
                    out[i, j] = ONE_BITS
                else:
                    if v >= vals.size:
                        return False
                    out[i, j] = vals[v]
                    v += 1
                z += 1
            k += 1
    return True


@njit(cache=True, nogil=True)
def decode(
    data: np.ndarray,
    offsets: np.ndarray,
    obs: np.ndarray,
    state: np.ndarray,
    reward: np.ndarray,
    actions: np.ndarray,
    avail: np.ndarray,
    wide_actions: bool,
) -> bool:
    """Decode an episode's buffer (`fill`'s layout, at `offsets`) into zero-filled outputs:
    obs uint32 [(T+1)*N, O], state uint32 [T+1, S], reward float32 [T], actions int64 [T*N],
    avail uint8 [(T+1)*N*A]. False when the buffer is inconsistent with its counts."""
    obs_vals = data[offsets[0] : offsets[1]].view(np.uint32)
    state_vals = data[offsets[1] : offsets[2]].view(np.uint32)
    if not _decode(data, obs_vals, offsets[4:8], obs):
        return False
    if not _decode(data, state_vals, offsets[7:11], state):
        return False
    reward[:] = data[offsets[2] : offsets[3]].view(np.float32)
    if wide_actions:
        actions[:] = data[offsets[3] : offsets[4]].view(np.int32)
    else:
        actions[:] = data[offsets[3] : offsets[4]]
    if (avail.size + 7) >> 3 != offsets[11] - offsets[10]:
        return False
    for i in range(avail.size):
        avail[i] = _bit(data, offsets[10], i)
    return True


# check_values' return codes, in the order `Episode.validate` reports them
VALUES_OK, OBS_NONFINITE, STATE_NONFINITE, REWARD_NONFINITE, ACTION_RANGE, AVAIL_STUCK = range(6)
NONFINITE_FIELDS = {OBS_NONFINITE: "obs", STATE_NONFINITE: "state", REWARD_NONFINITE: "reward"}
OUT_OF_BOUNDS = 6  # the offsets pass the buffer's end (`check_layout` refuses such episodes)
_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], np.int64)


@njit(cache=True, nogil=True)
def check_bits(data: np.ndarray, offsets: np.ndarray, expect: np.ndarray) -> int:
    """The index (0..5) of the first bit section of an episode's buffer (obs live, nonzero,
    ones, then state's, at `offsets[4:10]`) whose set bits differ from `expect[k, 0]` or
    which has a set padding bit after its `expect[k, 1]` used bits; -1 when every section
    agrees, -2 when the offsets pass the buffer's end."""
    if offsets[10] > data.size:
        return -2
    for k in range(6):
        lo, hi = offsets[4 + k], offsets[5 + k]
        total = 0
        for p in range(lo, hi):
            total += _POPCOUNT[data[p]]
        pad = -expect[k, 1] % 8  # the lowest bits of the last byte (big-endian bit order)
        if total != expect[k, 0] or (pad and hi > lo and data[hi - 1] & ((1 << pad) - 1)):
            return k
    return -1


@njit(cache=True, nogil=True)
def _all_finite(data: np.ndarray, lo: int, hi: int) -> bool:
    """Whether the little-endian float32s in data[lo:hi] are finite (exponent bits not all
    set), read byte by byte: a buffer viewing a received frame need not be aligned."""
    for p in range(lo, hi, 4):  # noqa: SIM110 (a plain loop is what numba compiles best)
        if (data[p + 3] & 0x7F) == 0x7F and data[p + 2] >= 0x80:
            return False
    return True


@njit(cache=True, nogil=True)
def check_values(
    data: np.ndarray, offsets: np.ndarray, t: int, n: int, a: int, n_actions: int
) -> tuple[int, int]:
    """`Episode.validate`'s checks of the values, on an episode's buffer (`fill`'s layout,
    at `offsets`): (code, row) with code VALUES_OK or the first failing check's, and for
    AVAIL_STUCK the first (step * N + agent) row with no available action."""
    if offsets[11] > data.size:
        return OUT_OF_BOUNDS, 0
    for s in range(3):  # obs values, state values, reward
        if not _all_finite(data, offsets[s], offsets[s + 1]):
            return OBS_NONFINITE + s, 0
    lo = offsets[3]
    if a > 256:  # int32, little-endian
        for i in range(t * n):
            p = lo + 4 * i
            v = np.int64(data[p]) | (np.int64(data[p + 1]) << 8) | (np.int64(data[p + 2]) << 16)
            v |= np.int64(data[p + 3]) << 24
            if v >= 2**31:
                v -= 2**32
            if v < 0 or v >= n_actions:
                return ACTION_RANGE, 0
    else:
        for i in range(t * n):
            if data[lo + i] >= n_actions:
                return ACTION_RANGE, 0
    if ((t + 1) * n * a + 7) >> 3 > offsets[11] - offsets[10]:
        return OUT_OF_BOUNDS, 0
    for r in range((t + 1) * n):
        found = False
        for j in range(a):
            if _bit(data, offsets[10], r * a + j):
                found = True
                break
        if not found:
            return AVAIL_STUCK, r
    return VALUES_OK, 0

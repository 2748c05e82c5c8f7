"""The buffer service wire codec: msgpack frames, raw-byte arrays, no pickle anywhere.

Frame layout (both directions)::

    [4-byte big-endian unsigned length L][L bytes: one msgpack map]

Every request map carries ``op`` (str) and ``v`` (protocol version, int) plus op fields;
every reply carries ``ok`` (bool) and, when ``ok`` is false, ``error`` (a short code from
`ERROR_CODES`) and ``message``. A numpy array travels as ``{"dtype": "<f4", "shape": [..],
"data": <msgpack bin>}``: the dtype string must be in `ALLOWED_DTYPES` and
``prod(shape) * itemsize == len(data)``, otherwise decoding raises `CodecError`.

Episodes travel packed (`buffer_service.packed.PackedEpisode`, protocol 2): ``{"packing":
PACKING, "length", "dims", "obs_counts", "state_counts", "terminated", "data": <uint8
array>, actor_id, episode_seq, policy_version}``, the form the buffer stores, logs and
snapshots. Protocol 1's dense episode map (seven arrays, as `Episode` holds them), which logs
and snapshots written before packing hold, is still read, and packed on reading; a packing
this build does not know is refused with `PackingError`.

Zero-copy: `buffer_service.wire` encodes array data as references (the socket or one join
copies them once) and decodes bins as memoryview slices of the received frame, which
``np.frombuffer`` wraps without copying; decoded arrays therefore alias the frame buffer
(read-only when it is ``bytes``). `own` copies an episode out when that matters.
"""

from __future__ import annotations

import math
import struct
from typing import Any

import msgpack
import numpy as np

from buffer_service import wire
from buffer_service.episode import (
    EPISODE_ARRAYS,
    EPISODE_DTYPES,
    EPISODE_SCALARS,
    Episode,
    EpisodeError,
)
from buffer_service.packed import PACKING, FloatCounts, PackedEpisode

PROTOCOL_VERSION = 2  # 2: episodes packed (1: dense arrays, still read from old logs)
FRAME_HEADER = struct.Struct(">I")
MAX_NDIM = 8
ZERO_COPY_MIN = 4 * 2**20  # frames this large are decoded without copying array data
INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1

# Explicit byte order in every dtype string, so a big-endian peer cannot be misread.
ALLOWED_DTYPES: frozenset[str] = frozenset({"<f4", "<f8", "|u1", "|b1", "<i4", "<i8"})

ERROR_CODES: frozenset[str] = frozenset(
    {
        "bad_frame",  # not msgpack, not a map, missing/ill-typed/unknown fields, bad arrays
        "frame_too_large",  # declared length above max_frame_bytes (max_hello_bytes before hello)
        "bad_version",  # `v` differs from PROTOCOL_VERSION
        "auth",  # wrong or missing token
        "hello_required",  # an op other than hello before a successful hello
        "unknown_op",
        "schema_mismatch",  # hello schema differs from the server's
        "invalid_episode",  # an episode breaks the schema (shape, dtype, NaN/inf, ...)
        "no_table",  # a table name the server does not have
        "rate_limited",  # the rate limiter did not allow the op within its timeout
        "bad_request",  # out-of-range values: batch_size above the cap, empty or repeated tables
        "storage_full",  # the log could not be written (no space): nothing was stored
        "too_many_connections",  # the client holds max_connections_per_client already
        "internal",
    }
)


class CodecError(ValueError):
    """A frame or array that does not follow the wire format."""


class PackingError(CodecError):
    """A packed episode in a layout (`packing`) that this build cannot read: written by a
    newer version of the buffer service."""


PACKED_KEYS = frozenset(
    {"packing", "length", "dims", "obs_counts", "state_counts", "terminated", "data"}
    | set(EPISODE_SCALARS)
)


def encode_array(arr: np.ndarray) -> dict[str, Any]:
    """Wire form of `arr` (C-contiguous, little-endian); the data is not copied here.

    Args:
        arr: any numpy array whose dtype is in ALLOWED_DTYPES after byte-order normalising.

    Returns:
        ``{"dtype", "shape", "data"}`` with ``data`` a memoryview msgpack packs as bin.
    """
    if arr.dtype.byteorder == ">":
        arr = arr.astype(arr.dtype.newbyteorder("<"))
    if not arr.flags.c_contiguous:  # (np.ascontiguousarray would turn 0-d into 1-d)
        arr = arr.copy(order="C")
    dtype = arr.dtype.str
    if dtype not in ALLOWED_DTYPES:
        raise CodecError(f"dtype {dtype} is not in the wire allow-list {sorted(ALLOWED_DTYPES)}")
    data = memoryview(arr.reshape(-1).view(np.uint8)) if arr.size else b""
    return {"dtype": dtype, "shape": list(arr.shape), "data": data}


def decode_array(obj: Any, name: str = "array") -> np.ndarray:
    """Validate and wrap one wire array without copying its bytes.

    Args:
        obj: the unpacked ``{"dtype", "shape", "data"}`` map.
        name: field name for error messages.

    Returns:
        A read-only array viewing ``data``.
    """
    if not isinstance(obj, dict) or set(obj) != {"dtype", "shape", "data"}:
        raise CodecError(f"{name}: an array must be a map with exactly dtype, shape, data")
    dtype, shape, data = obj["dtype"], obj["shape"], obj["data"]
    if not isinstance(dtype, str) or dtype not in ALLOWED_DTYPES:
        raise CodecError(f"{name}: dtype {dtype!r} is not in the allow-list")
    if not isinstance(shape, list) or len(shape) > MAX_NDIM:
        raise CodecError(f"{name}: shape must be a list of at most {MAX_NDIM} ints")
    if not all(type(d) is int and 0 <= d < 2**40 for d in shape):
        raise CodecError(f"{name}: shape {shape!r} must hold non-negative ints")
    if not isinstance(data, (bytes, memoryview)):
        raise CodecError(f"{name}: data must be msgpack bin")
    dt = np.dtype(dtype)
    nbytes = data.nbytes if isinstance(data, memoryview) else len(data)
    if math.prod(shape) * dt.itemsize != nbytes:
        raise CodecError(f"{name}: shape {shape} x itemsize {dt.itemsize} != {nbytes} data bytes")
    arr = np.frombuffer(data, dtype=dt).reshape(shape)
    if dt == np.bool_ and arr.size and int(arr.view(np.uint8).max()) > 1:
        raise CodecError(f"{name}: bool data holds bytes other than 0 and 1")
    return arr


def episode_to_wire(ep: Episode | PackedEpisode) -> dict[str, Any]:
    """Wire map of one episode, packed (a dense `Episode` is packed here, state kept)."""
    p = PackedEpisode.pack(ep)
    out: dict[str, Any] = {
        "packing": PACKING,
        "length": p.length,
        "dims": list(p.dims),
        "obs_counts": _counts_list(p.obs_counts),
        "state_counts": _counts_list(p.state_counts),
        "terminated": p.terminated_last,
        "data": encode_array(p.data),
    }
    for name in EPISODE_SCALARS:
        out[name] = int(getattr(p, name))
    return out


def dense_to_wire(ep: Episode) -> dict[str, Any]:
    """Protocol 1's wire map of one episode (its seven arrays and three integer tags): what
    logs and snapshots written before packing hold; kept to test that they are still read."""
    out: dict[str, Any] = {name: encode_array(getattr(ep, name)) for name in EPISODE_ARRAYS}
    for name in EPISODE_SCALARS:
        out[name] = int(getattr(ep, name))
    return out


def _counts_list(c: FloatCounts) -> list[int]:
    return [c.rows, c.features, c.live, c.nonzero, c.values]


def episode_from_wire(obj: Any) -> PackedEpisode:
    """The stored form of an episode from its wire map, packed or (protocol 1) dense; checks
    keys, dtypes, tag ranges and the packed layout (not the schema: `validate`'s job).

    Raises:
        PackingError: a packing this build does not know.
        CodecError: anything else that is not an episode's wire map.
    """
    if isinstance(obj, dict) and "packing" in obj:
        return _packed_from_wire(obj)
    dense = dense_from_wire(obj)
    try:
        return PackedEpisode.pack(dense)
    except EpisodeError as e:
        raise CodecError(str(e)) from None


def _ints(obj: Any, n: int, name: str, low: int = 0) -> list[int]:
    if not (isinstance(obj, list) and len(obj) == n):
        raise CodecError(f"{name}: must be a list of {n} ints, got {obj!r}")
    if not all(type(v) is int and low <= v < 2**40 for v in obj):
        raise CodecError(f"{name}: must hold ints in {low}..2**40, got {obj!r}")
    return obj


def _packed_from_wire(obj: dict[str, Any]) -> PackedEpisode:
    if obj["packing"] != PACKING:
        raise PackingError(
            f"episode packing {obj['packing']!r} is not one this build reads ({PACKING}): it "
            "was written by a newer buffer service; read it with that version"
        )
    if set(obj) != PACKED_KEYS:
        raise CodecError(f"packed episode must be a map with exactly {sorted(PACKED_KEYS)}")
    if type(obj["terminated"]) is not bool or type(obj["length"]) is not int:
        raise CodecError("packed episode: terminated must be a bool and length an int")
    data = decode_array(obj["data"], "data")
    if data.dtype != np.uint8 or data.ndim != 1:
        raise CodecError("packed episode: data must be a flat |u1 array")
    try:
        ep = PackedEpisode(
            length=obj["length"],
            dims=tuple(_ints(obj["dims"], 4, "dims")),
            obs_counts=FloatCounts(*_ints(obj["obs_counts"], 5, "obs_counts")),
            state_counts=FloatCounts(*_ints(obj["state_counts"], 5, "state_counts")),
            terminated_last=obj["terminated"],
            data=data,
            **_scalars(obj),
        )
        ep.check_layout()
    except EpisodeError as e:
        raise CodecError(str(e)) from None
    return ep


def _scalars(obj: dict[str, Any]) -> dict[str, int]:
    out = {}
    for name in EPISODE_SCALARS:
        val = obj[name]
        if type(val) is not int or not INT64_MIN <= val <= INT64_MAX:
            raise CodecError(f"{name}: must be an int64, got {val!r}")
        out[name] = val
    return out


def dense_from_wire(obj: Any) -> Episode:
    """Episode from its protocol-1 (dense) wire map; checks keys, dtypes, dimensions and tag
    ranges (not the schema)."""
    expected = set(EPISODE_ARRAYS) | set(EPISODE_SCALARS)
    if not isinstance(obj, dict) or set(obj) != expected:
        got = sorted(obj) if isinstance(obj, dict) else type(obj).__name__
        raise CodecError(f"episode must be a map with exactly {sorted(expected)}, got {got}")
    fields_: dict[str, Any] = {}
    for name in EPISODE_ARRAYS:
        arr = decode_array(obj[name], name)
        if arr.dtype != EPISODE_DTYPES[name]:
            raise CodecError(f"{name}: dtype {arr.dtype} but episodes need {EPISODE_DTYPES[name]}")
        fields_[name] = arr
    ep = Episode(**fields_, **_scalars(obj))
    t = ep.actions.shape[0] if ep.actions.ndim else 0
    ndims = {"obs": 3, "state": 2, "avail_actions": 3, "actions": 2}
    for name in EPISODE_ARRAYS:
        arr, steps = fields_[name], t + 1 if name in ("obs", "state", "avail_actions") else t
        if arr.ndim != ndims.get(name, 1) or arr.shape[0] != steps or t < 1:
            raise CodecError(f"{name}: shape {arr.shape} is not that of an episode of {t} steps")
    return ep


def pack(msg: dict[str, Any]) -> bytes:
    """msgpack body of one frame (without the length prefix), as one buffer."""
    return wire.encode(msg)


def pack_parts(msg: dict[str, Any]) -> list[bytes | memoryview]:
    """msgpack body of one frame as buffers that reference large array data (no copy)."""
    return wire.encode_parts(msg)


def pack_contiguous(msg: dict[str, Any]) -> np.ndarray:
    """msgpack body of one frame in one fresh uint8 buffer: each array byte copied once.

    Same bytes as `pack`; copies through numpy (no zero-fill, no intermediate bytes).
    """
    parts = wire.encode_parts(msg)
    views = [np.frombuffer(p, np.uint8) for p in parts]
    out = np.empty(sum(v.size for v in views), np.uint8)
    pos = 0
    for v in views:
        out[pos : pos + v.size] = v
        pos += v.size
    return out


def unpack(body: bytes | bytearray | memoryview) -> dict[str, Any]:
    """Parse one frame body into a map; raise CodecError on anything else.

    Frames of at least ZERO_COPY_MIN bytes are parsed by `wire.decode`, whose bins are
    memoryview slices of `body` (no copy); smaller ones by the msgpack C library (bins
    copied into bytes, cheap at that size, and much less per-item overhead). Hostile bodies
    cannot expand either way: container sizes are bounded by the bytes left.
    """
    try:
        if decodes_as_views(memoryview(body).nbytes):
            msg = wire.decode(body)
        else:  # small frames: the C library is faster and the copies are cheap
            msg = msgpack.unpackb(body, raw=False, strict_map_key=True)
    except Exception as e:  # msgpack raises several unrelated types on garbage
        raise CodecError(f"not a msgpack frame: {type(e).__name__}: {e}") from None
    if not isinstance(msg, dict):
        raise CodecError(f"frame must be a msgpack map, got {type(msg).__name__}")
    return msg


def decodes_as_views(nbytes: int) -> bool:
    """Does `unpack` return a frame of `nbytes` with bins that view it (not copies)?"""
    return nbytes >= ZERO_COPY_MIN


def own(ep: Episode | PackedEpisode) -> Episode | PackedEpisode:
    """A copy of `ep` whose arrays own their memory (not views of a received frame)."""
    if isinstance(ep, PackedEpisode):
        return ep.owned()
    arrays = {name: np.array(getattr(ep, name)) for name in EPISODE_ARRAYS}
    return Episode(**arrays, **{name: getattr(ep, name) for name in EPISODE_SCALARS})


def frame(body: bytes) -> bytes:
    """The 4-byte length prefix for `body`."""
    if len(body) > 0xFFFFFFFF:
        raise CodecError(f"frame of {len(body)} bytes exceeds the 4 GiB prefix")
    return FRAME_HEADER.pack(len(body))


def error_reply(code: str, message: str) -> dict[str, Any]:
    """The reply map for a refused request."""
    assert code in ERROR_CODES, code
    return {"ok": False, "v": PROTOCOL_VERSION, "error": code, "message": message}

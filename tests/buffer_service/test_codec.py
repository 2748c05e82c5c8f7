"""Wire codec: round trips and the rejection table."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from buffer_service import codec
from buffer_service.codec import CodecError, PackingError
from buffer_service.packed import PackedEpisode
from tests.buffer_service.conftest import SCHEMA, make_episode


@pytest.mark.parametrize(
    "arr",
    [
        np.arange(24, dtype=np.float32).reshape(2, 3, 4),
        np.array([True, False, True]),
        np.zeros((0, 5), np.int64),
        np.arange(10, dtype=np.uint8)[::2],  # non-contiguous
        np.arange(6, dtype=">i8"),  # big-endian is normalised
        np.float64(3.5) * np.ones(()),
    ],
)
def test_array_round_trip(arr):
    back = codec.decode_array(codec.unpack(codec.pack({"a": codec.encode_array(arr)}))["a"])
    assert back.shape == arr.shape
    assert back.dtype == arr.dtype.newbyteorder("<") or back.dtype == arr.dtype
    np.testing.assert_array_equal(back, arr)


def test_decoded_array_views_received_bytes():
    wire = codec.unpack(codec.pack({"a": codec.encode_array(np.ones(1000, np.float32))}))["a"]
    arr = codec.decode_array(wire)
    assert not arr.flags.writeable  # np.frombuffer over msgpack's bytes: no extra copy
    assert arr.base is not None


def test_episode_round_trip():
    ep = make_episode(actor=3, seq=17, t=4)
    back = codec.episode_from_wire(codec.unpack(codec.pack(codec.episode_to_wire(ep))))
    back.validate(SCHEMA)
    assert back.key == (3, 17) and back.policy_version == ep.policy_version
    for name in codec.EPISODE_ARRAYS:
        np.testing.assert_array_equal(getattr(back, name), getattr(ep, name))


def _arr(dtype="<f4", shape=(2,), data=b"\0" * 8):
    return {"dtype": dtype, "shape": list(shape), "data": data}


@pytest.mark.parametrize(
    ("obj", "why"),
    [
        ({"dtype": "<f4", "shape": [2]}, "exactly"),
        (_arr(dtype="|O"), "allow-list"),  # object arrays would mean pickle
        (_arr(dtype="<c8"), "allow-list"),
        (_arr(dtype=5), "allow-list"),
        (_arr(shape=(3,)), "data bytes"),  # 3*4 != 8
        (_arr(shape=(-2,)), "non-negative"),
        ({"dtype": "<f4", "shape": "2", "data": b"\0" * 8}, "list"),
        (_arr(shape=(1,) * 9, data=b"\0" * 4), "at most"),
        (_arr(data="notbytes"), "bin"),
        (_arr(dtype="|b1", shape=(2,), data=b"\x00\x07"), "bool"),
        ([1, 2], "exactly"),
    ],
)
def test_array_rejections(obj, why):
    with pytest.raises(CodecError, match=why):
        codec.decode_array(obj)


def test_dense_episodes_of_protocol_1_are_read_and_packed():
    """Logs and snapshots written before packing hold dense episodes: still read, packed."""
    ep = make_episode(actor=2, seq=5, t=4)
    back = codec.episode_from_wire(codec.unpack(codec.pack(codec.dense_to_wire(ep))))
    assert isinstance(back, PackedEpisode)
    back.validate(SCHEMA)
    for name in codec.EPISODE_ARRAYS:
        assert getattr(back, name).tobytes() == getattr(ep, name).tobytes(), name


def test_packed_episode_rejections():
    wire = codec.unpack(codec.pack(codec.episode_to_wire(make_episode(t=4))))
    with pytest.raises(PackingError, match="packing 9 is not one this build reads"):
        codec.episode_from_wire(dict(wire, packing=9))
    with pytest.raises(CodecError, match="exactly"):
        codec.episode_from_wire({k: v for k, v in wire.items() if k != "dims"})
    with pytest.raises(CodecError, match="data holds"):  # one byte short
        data = codec.decode_array(wire["data"])[:-1].copy()
        codec.episode_from_wire(dict(wire, data=codec.encode_array(data)))
    counts = list(wire["obs_counts"])
    counts[4] -= 1  # one stored value fewer than the ones bits leave
    with pytest.raises(CodecError):
        codec.episode_from_wire(dict(wire, obs_counts=counts))
    with pytest.raises(CodecError, match="ints"):
        codec.episode_from_wire(dict(wire, dims=[3, -1, 6, 5]))
    with pytest.raises(CodecError, match="int64"):
        codec.episode_from_wire(dict(wire, actor_id="x"))


def test_episode_rejections():
    wire = codec.dense_to_wire(make_episode())
    wire = codec.unpack(codec.pack(wire))
    bad_dtype = dict(wire, actions=codec.encode_array(np.zeros((5, 3), np.int32)))
    with pytest.raises(CodecError, match="actions"):
        codec.episode_from_wire(codec.unpack(codec.pack(bad_dtype)))
    with pytest.raises(CodecError, match="exactly"):
        codec.episode_from_wire({k: v for k, v in wire.items() if k != "reward"})
    with pytest.raises(CodecError, match="int64"):
        codec.episode_from_wire(dict(wire, actor_id="x"))
    with pytest.raises(CodecError, match="int64"):
        codec.episode_from_wire(dict(wire, episode_seq=2**64 - 1))


@pytest.mark.parametrize(
    "body",
    [b"", b"\xc1", b"\x93\x01\x02\x03", msgpack.packb("str"), b"\x85", msgpack.packb({1: 2})],
)
def test_unpack_rejects_non_maps_and_garbage(body):
    with pytest.raises(CodecError):
        codec.unpack(body)


def test_error_reply_codes_are_known():
    with pytest.raises(AssertionError):
        codec.error_reply("no_such_code", "x")
    assert codec.error_reply("auth", "m")["ok"] is False


def test_large_frames_decode_without_copying():
    big = np.arange(codec.ZERO_COPY_MIN // 4 + 10, dtype=np.float32)
    body = codec.pack({"a": codec.encode_array(big)})
    assert codec.pack_contiguous({"a": codec.encode_array(big)}).tobytes() == body
    back = codec.decode_array(codec.unpack(body)["a"])
    np.testing.assert_array_equal(back, big)
    assert np.shares_memory(back, np.frombuffer(body, np.uint8))  # a view of the frame

"""The zero-copy msgpack subset reads and writes what the msgpack library does."""

from __future__ import annotations

import contextlib
import random

import msgpack
import pytest

from buffer_service import wire

VALUES = [
    None,
    True,
    False,
    0,
    127,
    128,
    -1,
    -32,
    -33,
    255,
    256,
    65535,
    65536,
    2**32,
    2**63 - 1,
    -(2**63),
    2**64 - 1,
    1.5,
    -0.0,
    float("inf"),
    "",
    "é" * 40,
    "x" * 300,
    "y" * 70_000,
    b"",
    b"\x00" * 20,
    b"z" * 300,
    b"w" * 70_000,
    [],
    list(range(20)),
    {"a": 1, "b": [1, 2, {"c": b"d"}]},
    {f"k{i}": i for i in range(40)},
    list(range(70_000)),
]


@pytest.mark.parametrize("value", VALUES, ids=range(len(VALUES)))
def test_interoperates_with_msgpack(value):
    ours = wire.encode(value)
    assert msgpack.unpackb(ours, raw=False) == value
    back = wire.decode(msgpack.packb(value, use_bin_type=True))
    if isinstance(value, bytes):
        assert isinstance(back, memoryview) and back.tobytes() == value
    else:
        assert back == value or (back != back and value != value)


def test_large_bins_are_referenced_not_copied():
    data = bytearray(b"q" * (wire.REF_MIN + 5))
    parts = wire.encode_parts({"data": memoryview(data)})
    assert any(isinstance(p, memoryview) and p.obj is data for p in parts)
    out = wire.decode(b"".join(parts))["data"]
    assert isinstance(out, memoryview) and out.nbytes == len(data)


@pytest.mark.parametrize(
    "data",
    [
        b"",
        b"\xc1",
        b"\xc7\x01\x00\x00",  # ext 8
        b"\xd4\x00\x00",  # fixext 1
        b"\xc4\x05ab",  # bin shorter than declared
        b"\xdd\xff\xff\xff\xff",  # array bomb
        b"\xdf\x7f\xff\xff\xff",  # map bomb
        b"\x81\x01\x02",  # int map key
        b"\xa2\xff\xfe",  # invalid utf-8
        b"\x91" * 40 + b"\xc0",  # too deep
        b"\xc0\xc0",  # trailing bytes
        b"\xcd\x01",  # truncated uint16
    ],
)
def test_rejects_malformed(data):
    with pytest.raises(wire.WireError):
        wire.decode(data)


def test_random_bytes_never_crash():
    rng = random.Random(7)
    for _ in range(2000):
        blob = rng.randbytes(rng.randrange(0, 64))
        with contextlib.suppress(wire.WireError):
            wire.decode(blob)


def test_encode_refuses_non_string_keys():
    with pytest.raises(wire.WireError):
        wire.encode({1: 2})

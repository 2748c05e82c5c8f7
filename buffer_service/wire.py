"""A zero-copy subset of msgpack, written from the msgpack spec.

Why not only the msgpack library: ``msgpack.packb`` copies every bin into a growing
buffer and ``unpackb`` copies every bin into a new ``bytes``; for episode frames (hundreds
of MB of array data) those copies dominated. Here encoding returns a list of buffers in
which large bins are *references* to the arrays' memory (send them with
``sendmsg``/``writelines`` or join them once), and decoding returns bins as memoryview
slices of the received frame (``np.frombuffer`` then wraps them without a copy).

The output is ordinary msgpack (any msgpack library reads it and vice versa) restricted to
nil, bool, int, float, str, bin, array and map with string keys; ext types and the
reserved byte are refused. Decoding is hardened for hostile input: every length is checked
against the bytes left, containers are bounded by the remaining bytes, nesting by
`MAX_DEPTH`, and trailing bytes are an error.
"""

from __future__ import annotations

import struct
from typing import Any

import msgpack

MAX_DEPTH = 32
REF_MIN = 32 * 1024  # bins at least this long are referenced, not copied

_U8, _U16, _U32 = struct.Struct(">B"), struct.Struct(">H"), struct.Struct(">I")
_F32, _F64 = struct.Struct(">f"), struct.Struct(">d")
_INTS = {
    0xCC: struct.Struct(">B"),
    0xCD: struct.Struct(">H"),
    0xCE: struct.Struct(">I"),
    0xCF: struct.Struct(">Q"),
    0xD0: struct.Struct(">b"),
    0xD1: struct.Struct(">h"),
    0xD2: struct.Struct(">i"),
    0xD3: struct.Struct(">q"),
}


class WireError(ValueError):
    """Bytes that are not a msgpack value of the supported subset."""


def _len_header(n: int, small: int | None, small_max: int, codes: tuple[int, int, int]) -> bytes:
    if small is not None and n <= small_max:
        return bytes([small | n])
    if n < 256 and codes[0]:
        return bytes([codes[0], n])
    if n < 65536:
        return bytes([codes[1]]) + _U16.pack(n)
    if n < 2**32:
        return bytes([codes[2]]) + _U32.pack(n)
    raise WireError(f"length {n} does not fit msgpack")


def encode_parts(obj: Any) -> list[bytes | memoryview]:
    """msgpack encoding of `obj` as a list of buffers; large bins are not copied."""
    parts: list[bytes | memoryview] = []
    buf = bytearray()

    def walk(o: Any, depth: int) -> None:
        nonlocal buf
        if depth > MAX_DEPTH:
            raise WireError("nesting too deep")
        if isinstance(o, (bytes, bytearray, memoryview)):
            n = o.nbytes if isinstance(o, memoryview) else len(o)
            buf += _len_header(n, None, 0, (0xC4, 0xC5, 0xC6))
            if n >= REF_MIN:
                parts.append(bytes(buf))
                buf = bytearray()
                parts.append(o if isinstance(o, memoryview) else memoryview(o))
            else:
                buf += o
        elif isinstance(o, dict):
            buf += _len_header(len(o), 0x80, 15, (0, 0xDE, 0xDF))
            for k, v in o.items():
                if not isinstance(k, str):
                    raise WireError(f"map key {k!r} is not a string")
                walk(k, depth + 1)
                walk(v, depth + 1)
        elif isinstance(o, (list, tuple)):
            buf += _len_header(len(o), 0x90, 15, (0, 0xDC, 0xDD))
            for v in o:
                walk(v, depth + 1)
        else:  # nil, bool, int, float, str: the library's encoding is the reference
            buf += msgpack.packb(o, use_bin_type=True)

    walk(obj, 0)
    if buf:
        parts.append(bytes(buf))
    return parts


def encode(obj: Any) -> bytes:
    """msgpack encoding of `obj` as one buffer (one copy of every bin)."""
    return b"".join(encode_parts(obj))


class _Reader:
    def __init__(self, data: bytes | bytearray | memoryview) -> None:
        self.mv = memoryview(data).cast("B") if not isinstance(data, bytes) else memoryview(data)
        self.n = len(self.mv)
        self.pos = 0

    def take(self, k: int) -> memoryview:
        end = self.pos + k
        if end > self.n:
            raise WireError("truncated msgpack value")
        out = self.mv[self.pos : end]
        self.pos = end
        return out

    def unpack(self, st: struct.Struct) -> Any:
        return st.unpack(self.take(st.size))[0]

    def count(self, k: int) -> int:
        if k > self.n - self.pos:  # every element needs at least one byte
            raise WireError(f"container of {k} items in {self.n - self.pos} bytes")
        return k

    def value(self, depth: int) -> Any:
        if depth > MAX_DEPTH:
            raise WireError("nesting too deep")
        b = self.unpack(_U8)
        if b <= 0x7F:
            return b
        if b >= 0xE0:
            return b - 0x100
        if 0xA0 <= b <= 0xBF:
            return self.text(b & 0x1F)
        if 0x90 <= b <= 0x9F:
            return self.array(b & 0x0F, depth)
        if 0x80 <= b <= 0x8F:
            return self.map(b & 0x0F, depth)
        return self.tagged(b, depth)

    def tagged(self, b: int, depth: int) -> Any:
        if b == 0xC0:
            return None
        if b in (0xC2, 0xC3):
            return b == 0xC3
        if b in _INTS:
            return self.unpack(_INTS[b])
        if b == 0xCA:
            return self.unpack(_F32)
        if b == 0xCB:
            return self.unpack(_F64)
        if b in (0xC4, 0xC5, 0xC6):
            return self.take(self.unpack((_U8, _U16, _U32)[b - 0xC4]))
        if b in (0xD9, 0xDA, 0xDB):
            return self.text(self.unpack((_U8, _U16, _U32)[b - 0xD9]))
        if b in (0xDC, 0xDD):
            return self.array(self.unpack((_U16, _U32)[b - 0xDC]), depth)
        if b in (0xDE, 0xDF):
            return self.map(self.unpack((_U16, _U32)[b - 0xDE]), depth)
        raise WireError(f"unsupported msgpack type byte 0x{b:02x}")

    def text(self, k: int) -> str:
        try:
            return str(self.take(k), "utf-8")
        except UnicodeDecodeError as e:
            raise WireError(f"invalid utf-8 string: {e}") from None

    def array(self, k: int, depth: int) -> list:
        return [self.value(depth + 1) for _ in range(self.count(k))]

    def map(self, k: int, depth: int) -> dict:
        out = {}
        for _ in range(self.count(k)):
            key = self.value(depth + 1)
            if not isinstance(key, str):
                raise WireError(f"map key {key!r} is not a string")
            out[key] = self.value(depth + 1)
        return out


def decode(data: bytes | bytearray | memoryview) -> Any:
    """Parse exactly one msgpack value; bins come back as memoryview slices of `data`."""
    r = _Reader(data)
    out = r.value(0)
    if r.pos != r.n:
        raise WireError(f"{r.n - r.pos} trailing bytes after the msgpack value")
    return out

"""The record format of the buffer's log and snapshot files, and a reader that survives damage.

Format 2 (written since issue 14). A file is a sequence of records::

    magic "\\xd7CRb" | u8 kind | u32 meta length M | u32 body length B | u32 crc32(meta+body)
    | u32 crc32 of the 17 bytes before it | meta (msgpack, M bytes) | body (B bytes)

(integers big-endian). The first record of every file is a FILE record naming the format,
the file's role and generation, and the table configs that wrote it. The header's own
checksum means a record's length can be trusted once the header checks out: a record whose
payload is damaged is skipped by its length and the records after it are still read. A
damaged header is skipped by scanning for the next magic whose header checksum holds.

What a reader calls what it finds:

* *damaged*: bytes that are not an intact record, followed by an intact record, or at the end
  of the file but not explicable by an interrupted append. Reported with offset and size.
* *torn tail*: the end of the file after the last intact record when it can only be an
  append cut short (fewer bytes than a header, a header whose record runs past the end, or
  zero bytes). An insert whose record is torn was never acknowledged.

Format 1 (before issue 14): ``u32 length | u32 crc32(payload) | u8 kind | u32 meta length``
then the payload, no FILE record. It is still read (a damaged record is skipped by trusting
its length, as nothing better is possible there), so that older folders can be converted.
"""

from __future__ import annotations

import os
import struct
import zlib
from dataclasses import dataclass, field
from typing import Any

import msgpack

FORMAT = 2
MAGIC = b"\xd7CRb"
HEAD = struct.Struct(">4sBIII")  # magic, kind, meta length, body length, payload crc
HEAD_CRC = struct.Struct(">I")
HEAD_SIZE = HEAD.size + HEAD_CRC.size
LEGACY = struct.Struct(">IIBI")  # format 1: length, payload crc, kind, meta length

FILE, INSERT, SAMPLE, SCHEMA, HEADER, EPISODE, END = b"F", b"I", b"S", b"C", b"H", b"E", b"Z"
KINDS = frozenset(FILE + INSERT + SAMPLE + SCHEMA + HEADER + EPISODE + END)  # as ints


def encode(kind: bytes, meta: Any, body: bytes | bytearray | memoryview = b"") -> list:
    """One record as buffers (the body is not copied)."""
    m = msgpack.packb(meta, use_bin_type=True)
    head = HEAD.pack(MAGIC, kind[0], len(m), len(body), zlib.crc32(body, zlib.crc32(m)))
    parts = [head, HEAD_CRC.pack(zlib.crc32(head)), m]
    return [*parts, body] if len(body) else parts


def write(fd: int, kind: bytes, meta: Any, body: bytes | bytearray | memoryview = b"") -> int:
    """Append one record to `fd`; returns its size in bytes."""
    parts = encode(kind, meta, body)
    total = sum(len(p) for p in parts)
    done = os.writev(fd, parts)
    if done != total:  # short write (rare on regular files): finish it by hand
        rest = b"".join(bytes(p) for p in parts)[done:]
        while rest:
            rest = rest[os.write(fd, rest) :]
    return total


@dataclass
class Record:
    offset: int
    kind: bytes
    meta: Any
    body: memoryview


@dataclass
class Scan:
    """What a reader found in one file.

    Attributes:
        format: 2, 1 (legacy) or None (empty or nothing readable).
        records: the intact records in file order.
        damaged: ``(offset, size, reason)`` of every stretch that is not an intact record.
        torn: ``(offset, size)`` of a torn tail, or None.
        size: the file's size in bytes.
    """

    format: int | None
    records: list[Record] = field(default_factory=list)
    damaged: list[tuple[int, int, str]] = field(default_factory=list)
    torn: tuple[int, int] | None = None
    size: int = 0

    @property
    def intact_end(self) -> int:
        """Where the intact part ends (the length to truncate a torn tail to)."""
        return self.torn[0] if self.torn else self.size


def _header_at(data: bytes, pos: int) -> tuple[int, int, int, int] | None:
    """(kind, meta length, body length, payload crc) of a format-2 header at `pos`."""
    if pos + HEAD_SIZE > len(data) or data[pos : pos + 4] != MAGIC:
        return None
    (crc,) = HEAD_CRC.unpack_from(data, pos + HEAD.size)
    if zlib.crc32(data[pos : pos + HEAD.size]) != crc:
        return None
    _, kind, mlen, blen, pcrc = HEAD.unpack_from(data, pos)
    return kind, mlen, blen, pcrc


def _next_header(data: bytes, start: int) -> int | None:
    pos = data.find(MAGIC, start)
    while pos != -1:
        if _header_at(data, pos) is not None:
            return pos
        pos = data.find(MAGIC, pos + 1)
    return None


def _meta(payload: memoryview, mlen: int) -> Any:
    return msgpack.unpackb(payload[:mlen], raw=False, strict_map_key=False)


def _scan_v2(data: bytes, out: Scan) -> None:
    view, n, pos = memoryview(data), len(data), 0
    while pos < n:
        head = _header_at(data, pos)
        if head is None:
            nxt = _next_header(data, pos + 1)
            if nxt is None:
                if n - pos < HEAD_SIZE or not data[pos:].strip(b"\0"):
                    out.torn = (pos, n - pos)
                else:
                    out.damaged.append((pos, n - pos, "unreadable bytes up to the end"))
                return
            out.damaged.append((pos, nxt - pos, "unreadable record header"))
            pos = nxt
            continue
        kind, mlen, blen, pcrc = head
        end = pos + HEAD_SIZE + mlen + blen
        if end > n:
            nxt = _next_header(data, pos + 1)
            if nxt is None:
                out.torn = (pos, n - pos)
                return
            out.damaged.append((pos, nxt - pos, "record runs into the next one"))
            pos = nxt
            continue
        payload = view[pos + HEAD_SIZE : end]
        reason = None
        if zlib.crc32(payload) != pcrc:
            reason = "checksum mismatch"
        elif kind not in KINDS:
            reason = f"unknown record kind {kind}"
        else:
            try:
                out.records.append(Record(pos, bytes([kind]), _meta(payload, mlen), payload[mlen:]))
            except Exception as e:  # intact bytes that are not msgpack: a writer bug
                reason = f"unreadable metadata ({type(e).__name__})"
        if reason:
            out.damaged.append((pos, end - pos, reason))
        pos = end


def _scan_legacy(data: bytes, out: Scan) -> None:
    view, n, pos = memoryview(data), len(data), 0
    while pos < n:
        if n - pos < LEGACY.size:
            out.torn = (pos, n - pos)
            return
        length, crc, kind, mlen = LEGACY.unpack_from(data, pos)
        end = pos + LEGACY.size + length
        plausible = kind in KINDS and mlen <= length
        if not plausible:  # nothing to trust the length of: the rest is lost
            out.damaged.append((pos, n - pos, "unreadable record header (format 1)"))
            return
        if end > n:
            out.torn = (pos, n - pos)
            return
        payload = view[pos + LEGACY.size : end]
        try:
            if zlib.crc32(payload) != crc:
                raise ValueError("checksum mismatch")
            out.records.append(Record(pos, bytes([kind]), _meta(payload, mlen), payload[mlen:]))
        except Exception as e:
            out.damaged.append((pos, end - pos, f"{e} (format 1)"))
        pos = end


def _is_legacy(data: bytes) -> bool:
    if len(data) < LEGACY.size:
        return False
    length, crc, kind, mlen = LEGACY.unpack_from(data, 0)
    end = LEGACY.size + length
    if kind not in KINDS or mlen > length or end > len(data):
        return False
    return zlib.crc32(data[LEGACY.size : end]) == crc


def scan_bytes(data: bytes) -> Scan:
    """Every intact record of a file's contents, and what is wrong with the rest."""
    out = Scan(format=None, size=len(data))
    if not data:
        return out
    if _header_at(data, 0) is None and _is_legacy(data):
        out.format = 1
        _scan_legacy(data, out)
    else:
        _scan_v2(data, out)
        out.format = 2 if out.records else None
    return out


def scan_file(path: str) -> Scan:
    with open(path, "rb") as f:
        return scan_bytes(f.read())

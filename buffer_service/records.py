"""The record format of the buffer's log and snapshot files, and a reader that survives damage.

Format 2 (written since issue 14). A file is a sequence of records::

    magic "\\xd7CRb" | u8 kind | u32 meta length M | u32 body length B | u32 crc32(meta+body)
    | u32 crc32 of the 17 bytes before it | meta (msgpack, M bytes) | body (B bytes)

(integers big-endian). The first record of every file is a FILE record naming the format,
the file's role and generation, and the table configs that wrote it. The header's own
checksum means a record's length can be trusted once the header checks out: a record whose
payload is damaged is skipped by its length and the records after it are still read. A
damaged header is skipped by scanning for the next magic whose header checksum holds.

A reader (`scan_file`, `iter_file`) reads a file forward in bounded pieces, one record at a
time, so restoring a log needs memory for its largest record, not for the file.

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
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, BinaryIO

import msgpack

FORMAT = 2
MAGIC = b"\xd7CRb"
HEAD = struct.Struct(">4sBIII")  # magic, kind, meta length, body length, payload crc
HEAD_CRC = struct.Struct(">I")
HEAD_SIZE = HEAD.size + HEAD_CRC.size
CHUNK = 1 << 20  # bytes read at a time when searching past damage
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
        records: the intact records in file order (only when the scan keeps them).
        damaged: ``(offset, size, reason)`` of every stretch that is not an intact record.
        torn: ``(offset, size)`` of a torn tail, or None.
        size: the file's size in bytes.
        count: intact records; head_kinds: the kinds of the first two; last: the last one;
            kinds: how many of each kind (kept whether or not the records are).
    """

    format: int | None
    records: list[Record] = field(default_factory=list)
    damaged: list[tuple[int, int, str]] = field(default_factory=list)
    torn: tuple[int, int] | None = None
    size: int = 0
    count: int = 0
    head_kinds: list[bytes] = field(default_factory=list)
    last: Record | None = None
    kinds: dict[bytes, int] = field(default_factory=dict)

    @property
    def intact_end(self) -> int:
        """Where the intact part ends (the length to truncate a torn tail to)."""
        return self.torn[0] if self.torn else self.size

    def add(self, rec: Record, keep: bool) -> None:
        self.count += 1
        if len(self.head_kinds) < 2:
            self.head_kinds.append(rec.kind)
        self.last = rec
        self.kinds[rec.kind] = self.kinds.get(rec.kind, 0) + 1
        if keep:
            self.records.append(rec)


def _header_at(data: bytes, pos: int) -> tuple[int, int, int, int] | None:
    """(kind, meta length, body length, payload crc) of a format-2 header at `pos`."""
    if pos + HEAD_SIZE > len(data) or data[pos : pos + 4] != MAGIC:
        return None
    (crc,) = HEAD_CRC.unpack_from(data, pos + HEAD.size)
    if zlib.crc32(data[pos : pos + HEAD.size]) != crc:
        return None
    _, kind, mlen, blen, pcrc = HEAD.unpack_from(data, pos)
    return kind, mlen, blen, pcrc


def _meta(payload: memoryview, mlen: int) -> Any:
    return msgpack.unpackb(payload[:mlen], raw=False, strict_map_key=False)


class _File:
    """A file read forward in pieces of at most `CHUNK` bytes (beside one record at a time),
    so that scanning needs memory for the largest record, not for the file."""

    def __init__(self, f: BinaryIO, size: int) -> None:
        self.f, self.n = f, size

    def read(self, pos: int, k: int) -> bytes:
        self.f.seek(pos)
        return self.f.read(k)

    def next_header(self, start: int) -> int | None:
        """The offset of the next intact format-2 header at or after `start`."""
        pos = start
        while pos < self.n:
            window = self.read(pos, CHUNK + HEAD_SIZE)
            i = window.find(MAGIC)
            while i != -1 and i < CHUNK:
                if _header_at(window, i) is not None:
                    return pos + i
                i = window.find(MAGIC, i + 1)
            pos += CHUNK
        return None

    def zeros_from(self, pos: int) -> bool:
        while pos < self.n:
            if self.read(pos, CHUNK).strip(b"\0"):
                return False
            pos += CHUNK
        return True


def _scan_v2(src: _File, out: Scan) -> Iterator[Record]:
    n, pos = src.n, 0
    while pos < n:
        head = _header_at(src.read(pos, HEAD_SIZE), 0)
        if head is None:
            nxt = src.next_header(pos + 1)
            if nxt is None:
                if n - pos < HEAD_SIZE or src.zeros_from(pos):
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
            nxt = src.next_header(pos + 1)
            if nxt is None:
                out.torn = (pos, n - pos)
                return
            out.damaged.append((pos, nxt - pos, "record runs into the next one"))
            pos = nxt
            continue
        payload = memoryview(src.read(pos + HEAD_SIZE, mlen + blen))
        reason = None
        if zlib.crc32(payload) != pcrc:
            reason = "checksum mismatch"
        elif kind not in KINDS:
            reason = f"unknown record kind {kind}"
        else:
            try:
                rec = Record(pos, bytes([kind]), _meta(payload, mlen), payload[mlen:])
            except Exception as e:  # intact bytes that are not msgpack: a writer bug
                reason = f"unreadable metadata ({type(e).__name__})"
            else:
                yield rec
        if reason:
            out.damaged.append((pos, end - pos, reason))
        pos = end


def _scan_legacy(data: bytes, out: Scan) -> Iterator[Record]:
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
            rec = Record(pos, bytes([kind]), _meta(payload, mlen), payload[mlen:])
        except Exception as e:
            out.damaged.append((pos, end - pos, f"{e} (format 1)"))
        else:
            yield rec
        pos = end


def _is_legacy(src: _File) -> bool:
    """Does the file start with an intact format-1 record? (Reads that record only.)"""
    head = src.read(0, LEGACY.size)
    if len(head) < LEGACY.size:
        return False
    length, crc, kind, mlen = LEGACY.unpack_from(head, 0)
    if kind not in KINDS or mlen > length or LEGACY.size + length > src.n:
        return False
    return zlib.crc32(src.read(LEGACY.size, length)) == crc


def iter_file(f: BinaryIO, out: Scan) -> Iterator[Record]:
    """Every intact record of an open file, in order, read in bounded pieces; what is wrong
    with the rest (and the file's format and size) lands in `out` as the records go by.
    Format-1 files (converted once, on the first start after an upgrade) are read whole."""
    out.size = n = f.seek(0, os.SEEK_END)
    if not n:
        return
    src = _File(f, n)
    if _header_at(src.read(0, HEAD_SIZE), 0) is None and _is_legacy(src):
        out.format = 1
        for rec in _scan_legacy(src.read(0, n), out):
            out.add(rec, keep=False)
            yield rec
        return
    for rec in _scan_v2(src, out):
        out.format = 2
        out.add(rec, keep=False)
        yield rec


def scan_file(path: str, keep: bool = True, visit: Callable[[Record], None] | None = None) -> Scan:
    """Read `path` record by record (memory: the largest record, not the file): every intact
    record (in ``records`` when `keep`; each handed to `visit` as it is read) and what is
    wrong with the rest."""
    out = Scan(format=None)
    with open(path, "rb") as f:
        for rec in iter_file(f, out):
            if keep:
                out.records.append(rec)
            if visit is not None:
                visit(rec)
    return out

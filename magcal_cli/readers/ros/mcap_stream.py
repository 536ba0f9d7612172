"""Stream an MCAP file's messages in bounded memory, skipping (and counting) corrupt chunks.

mcap's own readers stop at the first bad chunk (CRC, zstd/lz4 error) or broken record length. Here a chunk
that fails its CRC or does not decompress is skipped and counted, and when the record framing itself is
broken the reader resynchronises on the next chunk header whose lengths agree, as pymavlink does for
DataFlash. Only a file whose damage reaches its end (or that ends inside a record) counts as truncated.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import IO, Any

import numpy as np

from magcal_cli.progress import current
from magcal_cli.readers.cut import a_record
from magcal_cli.readers.ros.mcap_chunk import (
    Batch,
    ChunkError,
    RawIndex,
    decompress,
    from_messages,
    parse_records,
)
from magcal_cli.readers.ros.partial import MCAP_RECORDS, decompress_prefix

#: MCAP opcodes (spec: Records)
CHUNK_OPCODE, FOOTER_OPCODE = 0x06, 0x02
#: the footer record (opcode, length, summary start, summary offset start, summary CRC) and the closing magic
_FOOTER = struct.Struct("<BQQQI")
FOOTER_BYTES = _FOOTER.size + 8
#: a chunk header: opcode, record length, start/end time, uncompressed size, crc, then the compression name
_CHUNK_HEAD = struct.Struct("<BQQQQII")
#: compressions a chunk may name, as the length-prefixed string that follows the fixed header
COMPRESSIONS = (b"zstd", b"lz4", b"")
#: block size of the resynchronisation scan (bytes)
SCAN_BLOCK = 1 << 22
#: a chunk claiming to decompress to more than this is corrupt (writers use chunks of a few MB)
MAX_CHUNK_BYTES = 1 << 30
#: messages outside chunks (an unchunked file) are decoded this many at a time
LOOSE_BATCH = 4096

Defs = dict[int, Any]
Parsed = tuple[list[Any], Batch | None]          # a chunk's schema/channel records and its messages


@dataclass
class Damage:
    """What the stream skipped: corrupt chunks, bytes passed over while resynchronising, undecodable records."""

    chunks: int = 0
    bytes_skipped: int = 0
    orphans: int = 0
    truncated_at: int | None = None
    why: str = ""
    lost: str = ""

    def cut(self, fh: IO[bytes], at: int, size: int, why: str) -> Parsed:
        """Note that the file ends inside the record at `at`; the records a cut chunk there still holds."""
        self.truncated_at, self.why = at, why
        fh.seek(at)
        head = fh.read(_CHUNK_HEAD.size)
        name = MCAP_RECORDS.get(head[0], f"opcode 0x{head[0]:02x}") if head else "record"
        total = 9 + struct.unpack_from("<Q", head, 1)[0] if len(head) >= 9 else None
        present = f"{size - at} of its {total} bytes present" if total else f"{size - at} bytes present"
        self.lost = f"{a_record(name)}, {present}" if head else "it stops between records, before its footer"
        defs, batch = _chunk_prefix(fh, head, at, size) if name == "chunk" else ([], None)
        self.lost += f"; {len(batch)} messages recovered from it" if batch is not None and (defs or len(batch)) else ""
        return defs, batch

    def note(self) -> str:
        """The reader note for damage in the middle of the file, or "" when there was none."""
        parts = []
        if self.chunks:
            parts.append(f"{self.chunks} chunks that fail their CRC or do not decompress")
        if self.bytes_skipped:
            parts.append(f"{self.bytes_skipped} bytes with broken record framing")
        if self.orphans:
            parts.append(f"{self.orphans} messages of channels whose definition was lost")
        return f"corrupt data: skipped {', '.join(parts)}; reading resumed after each" if parts else ""


def _chunk_at(buf: bytes, i: int, size_left: int) -> bool:
    """True when a plausible chunk record starts at buf[i] (lengths consistent, known compression)."""
    if i + _CHUNK_HEAD.size > len(buf):
        return False
    op, length, start, end, _, _, name_len = _CHUNK_HEAD.unpack_from(buf, i)
    if op != CHUNK_OPCODE or end < start or length > size_left or name_len > 4:
        return False
    j = i + _CHUNK_HEAD.size
    name = buf[j:j + name_len]
    if name not in COMPRESSIONS or j + name_len + 8 > len(buf):
        return False
    (records_len,) = struct.unpack_from("<Q", buf, j + name_len)
    return bool(length == 8 * 3 + 4 + 4 + name_len + 8 + records_len)


def resync(fh: IO[bytes], start: int, size: int) -> int | None:
    """Offset of the next plausible chunk record at or after `start`, scanning in bounded blocks, or None."""
    pos = start
    overlap = _CHUNK_HEAD.size + 4 + 8
    while pos < size:
        fh.seek(pos)
        buf = fh.read(SCAN_BLOCK + overlap)
        i = buf.find(bytes([CHUNK_OPCODE]))
        while 0 <= i < min(len(buf), SCAN_BLOCK):
            if _chunk_at(buf, i, size - (pos + i)):
                return pos + i
            i = buf.find(bytes([CHUNK_OPCODE]), i + 1)
        if len(buf) <= SCAN_BLOCK:
            return None
        pos += SCAN_BLOCK
    return None


def summary_definitions(fh: IO[bytes], size: int) -> tuple[dict[int, Any], dict[int, Any]]:
    """Schemas and channels repeated in the summary section (empty when the footer or summary is damaged)."""
    from mcap.records import Channel, Footer, Schema
    from mcap.stream_reader import StreamReader

    schemas: dict[int, Any] = {}
    channels: dict[int, Any] = {}
    try:
        fh.seek(size - FOOTER_BYTES)
        op, _, summary_start, _, crc = _FOOTER.unpack(fh.read(_FOOTER.size))
        if op != FOOTER_OPCODE or not 0 < summary_start < size - FOOTER_BYTES or size - summary_start > SCAN_BLOCK:
            return schemas, channels
        fh.seek(summary_start)
        if crc and zlib.crc32(fh.read(size - 8 - 4 - summary_start)) != crc:    # CRC up to the CRC field itself
            return schemas, channels
        fh.seek(summary_start)
        for rec in StreamReader(fh, skip_magic=True, record_size_limit=size).records:
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                channels[rec.id] = rec
            elif isinstance(rec, Footer):
                break
    except Exception:  # noqa: BLE001 - a damaged summary only means no head start: stream as usual
        return {}, {}
    return schemas, channels


def iter_batches(fh: IO[bytes], size: int, damage: Damage) -> Iterator[tuple[Defs, Defs, Batch]]:
    """(schemas, channels, batch of their messages) of every readable chunk, in file order; damage is recorded."""
    from mcap.exceptions import EndOfFile, RecordLengthLimitExceeded
    from mcap.records import Chunk, Footer, Message

    schemas, channels = summary_definitions(fh, size)      # so a lost chunk does not orphan later messages
    hook = current()
    base, skip_magic = 0, False
    loose: list[Any] = []                                   # messages outside chunks, batched
    # the last chunk's records, parsed once the message indexes that follow it are read
    pending: list[tuple[bytes, list[RawIndex]]] = []

    def settle() -> Iterator[tuple[Defs, Defs, Batch]]:
        """The pending chunk's messages, then the loose ones (file order)."""
        while pending:
            data, index = pending.pop()
            try:
                parsed = parse_records(data, index=index)
            except Exception:  # noqa: BLE001 - a chunk whose record framing is broken: skipped
                damage.chunks += 1
                continue
            yield from _known(parsed, schemas, channels, damage)
        yield from _flush(loose, schemas, channels, damage)

    while True:
        fh.seek(base)
        reader = _reader(fh, skip_magic, size)
        stream = reader._stream                                     # noqa: SLF001 - its byte count locates damage
        records = reader.records
        while True:
            at = base + stream.count
            try:
                rec = next(records, None)
            except EndOfFile:
                yield from settle()
                yield from _known(damage.cut(fh, at, size, "it ends inside a record"), schemas, channels, damage)
                return
            except Exception as exc:  # noqa: BLE001 - any parse failure of the framing: resynchronise
                yield from settle()
                nxt = resync(fh, at + 1, size)
                if nxt is None:
                    cut = isinstance(exc, (struct.error, RecordLengthLimitExceeded))   # a length past the end
                    why = ("it ends inside a record" if cut else
                           f"the record framing is broken at byte {at}: {type(exc).__name__}")
                    tail = damage.cut(fh, at, size, why)
                    yield from _known(tail if cut else ([], None), schemas, channels, damage)
                    return
                damage.bytes_skipped += nxt - at
                base, skip_magic = nxt, True
                break
            if isinstance(rec, RawIndex):
                if pending:
                    pending[-1][1].append(rec)
                continue
            if rec is None or isinstance(rec, Footer):
                yield from settle()
                return
            if isinstance(rec, Message):
                yield from settle() if pending else iter(())
                loose.append(rec)
                if len(loose) >= LOOSE_BATCH:
                    yield from _flush(loose, schemas, channels, damage)
                continue
            yield from settle()
            if isinstance(rec, Chunk):
                hook("reading", at, size)
                try:
                    if rec.uncompressed_size > MAX_CHUNK_BYTES:
                        raise ChunkError(rec.uncompressed_size)
                    pending.append((decompress(rec), []))
                except Exception:  # noqa: BLE001 - a chunk that fails its CRC or does not decompress: skipped
                    damage.chunks += 1
                del rec                                         # the compressed bytes are no longer needed
                continue
            yield from _known(([rec], None), schemas, channels, damage)


def _reader(fh: IO[bytes], skip_magic: bool, size: int) -> Any:
    """mcap's StreamReader emitting chunks whole and message indexes as raw bytes.

    mcap parses an index entry (one per message) into a tuple, which cost more than decoding the messages."""
    from mcap.opcode import Opcode
    from mcap.stream_reader import StreamReader

    class _Reader(StreamReader):
        def _read_record(self, opcode: int, length: int) -> Any:
            if opcode == Opcode.MESSAGE_INDEX:
                return RawIndex(self._stream.read(length))      # parsed with numpy by its chunk
            return super()._read_record(opcode, length)

    return _Reader(fh, skip_magic=skip_magic, emit_chunks=True, record_size_limit=size)


def _flush(loose: list[Any], schemas: Defs, channels: Defs, damage: Damage) -> Iterator[tuple[Defs, Defs, Batch]]:
    """The batch of the messages found outside chunks so far (emptying `loose`)."""
    if loose:
        batch = from_messages(loose)
        loose.clear()
        yield from _known(([], batch), schemas, channels, damage)


def _known(parsed: Parsed, schemas: Defs, channels: Defs, damage: Damage) -> Iterator[tuple[Defs, Defs, Batch]]:
    """Learn the definitions among `parsed`; its messages of known channels (the others are counted as orphans)."""
    from mcap.records import Channel, Schema

    defs, batch = parsed
    for r in defs:
        if isinstance(r, Schema):
            schemas[r.id] = r
        elif isinstance(r, Channel):
            channels[r.id] = r
    if batch is None or not len(batch):
        return
    known = np.isin(batch.channel, np.fromiter(channels, dtype=np.int64, count=len(channels)))
    damage.orphans += int((~known).sum())
    yield schemas, channels, batch if bool(known.all()) else batch.select(known)


def _chunk_prefix(fh: IO[bytes], head: bytes, at: int, size: int) -> Parsed:
    """The complete records in the present part of a chunk cut by the end of the file (its CRC cannot be checked)."""
    if len(head) < _CHUNK_HEAD.size:
        return [], None
    name_len = _CHUNK_HEAD.unpack(head)[-1]
    fh.seek(at + _CHUNK_HEAD.size)
    name = fh.read(name_len)
    if name not in COMPRESSIONS:
        return [], None
    fh.seek(at + _CHUNK_HEAD.size + name_len + 8)
    data = decompress_prefix(fh.read(min(size - fh.tell(), MAX_CHUNK_BYTES)), name.decode())
    return parse_records(data, whole=False)

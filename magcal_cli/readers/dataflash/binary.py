"""Vectorised parser of binary DataFlash logs (ArduPilot `.bin`, PX4 `.px4log`): no Python loop per message.

A log is a chain of records `A3 95 <type> <payload>` whose lengths come from FMT records. The parser finds
every header candidate with numpy, reads the FMT records once, gives each candidate the index of the first
candidate at or after its end (its successor; a gap there means corrupt bytes, skipped as a resynchronising
reader would) and follows the chain from the first header by pointer doubling. Each wanted type is then
decoded in one `view` of a structured dtype over the gathered records.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Collection
from pathlib import Path

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from magcal_cli.progress import current
from magcal_cli.readers.cut import a_record
from magcal_cli.readers.dataflash.format import (
    FMT_ID,
    FMT_LENGTH,
    HEAD1,
    HEAD2,
    IntArray,
    MessageFormat,
    RawLog,
    Table,
    valid_format,
)

FMT_DTYPE = np.dtype([("Type", "u1"), ("Length", "u1"), ("Name", "S4"), ("Format", "S16"),
                      ("Columns", "S64")])
FMT_SELF = MessageFormat(FMT_ID, "FMT", FMT_LENGTH, "BBnNZ", ("Type", "Length", "Name", "Format", "Columns"))
#: types the reader always needs besides the caller's: units and multipliers
META_TYPES = ("FMTU", "UNIT", "MULT")
#: (offset of the FMT record, the format it defines)
Placed = tuple[int, MessageFormat]
CHUNK = 1 << 23
#: bytes parsed at a time, and the overlap that lets a record near a window's end be confirmed by the next two
WINDOW = 1 << 22
OVERLAP = 1024


def header_candidates(buf: np.ndarray) -> IntArray:
    """Offsets of every `A3 95` pair followed by at least a type byte (scanned in chunks to bound memory)."""
    parts = []
    end = buf.size - 2
    for lo in range(0, max(end, 0), CHUNK):
        hi = min(lo + CHUNK, end)
        hits = np.flatnonzero((buf[lo:hi] == HEAD1) & (buf[lo + 1:hi + 1] == HEAD2))
        parts.append(hits.astype(np.int64) + lo)
    return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)


def _header_prefix(buf: np.ndarray) -> int:
    """Length (0-2) of a record header cut off at the end of the file."""
    if buf.size >= 2 and buf[-2] == HEAD1 and buf[-1] == HEAD2:
        return 2
    return 1 if buf.size and buf[-1] == HEAD1 else 0


def _fmt_candidates(buf: np.ndarray, heads: IntArray) -> list[tuple[int, MessageFormat]]:
    """(offset, format) of every plausible FMT record, in file order."""
    at = heads[buf[heads + 2] == FMT_ID]
    at = at[at + FMT_LENGTH <= buf.size]
    if not at.size:
        return []
    recs = sliding_window_view(buf, FMT_LENGTH - 3)[at + 3].view(FMT_DTYPE)[:, 0]
    out = []
    for off, rec in zip(at.tolist(), recs, strict=False):            # FMT records: a few hundred per log
        try:
            name = rec["Name"].split(b"\0", 1)[0].decode("ascii")
            fmt = rec["Format"].split(b"\0", 1)[0].decode("ascii")
            cols = tuple(c for c in rec["Columns"].split(b"\0", 1)[0].decode("ascii").split(",") if c or fmt)
        except UnicodeDecodeError:
            continue
        length = int(rec["Length"])
        if int(rec["Type"]) != FMT_ID and valid_format(name, fmt, cols, length):
            out.append((off, MessageFormat(int(rec["Type"]), name, length, fmt, cols)))
    return out


def follow_chain(heads: IntArray, lengths: IntArray, size: int, trusted_start: bool = False) -> tuple[IntArray, IntArray]:
    """Offsets of the records on the chain from the first confirmed header, and their lengths.

    `size` is where the data end (the file size less a trailing partial header). With `trusted_start` a
    candidate at offset 0 starts the chain even unconfirmed (the previous window's chain leads to it).

    A candidate is confirmed when the next two records start exactly where their predecessors end (or the file
    ends), so a stray `A3 95` inside corrupt bytes is not taken for a record. succ[i] is the candidate at the
    end of i, else (corrupt bytes follow) the first confirmed candidate after it. The nodes reachable from the
    start are found by pointer doubling: after round k the frontier holds the nodes 2^k..2^(k+1)-1 steps
    away, so ceil(log2(chain length)) rounds of whole-array gathers suffice.
    """
    m = heads.size
    if m == 0:
        return heads, lengths
    ends = heads + lengths
    nxt = np.searchsorted(heads, ends, side="left")
    exact = heads[np.minimum(nxt, m - 1)] == ends
    exact &= nxt < m
    last = ends >= size
    nxt_c = np.minimum(nxt, m - 1)
    confirmed = np.flatnonzero(last | (exact & (exact[nxt_c] | last[nxt_c])))     # two records line up
    if confirmed.size == 0 and not (trusted_start and heads[0] == 0):
        return heads[:0], lengths[:0]
    resync = np.searchsorted(heads[confirmed], ends, side="left")
    succ = np.where(exact, nxt, np.append(confirmed, m)[resync])
    succ = np.append(succ, m)
    on = np.zeros(m + 1, dtype=bool)
    reached = np.zeros(1, dtype=np.int64) if trusted_start and heads[0] == 0 else confirmed[:1]
    on[reached] = True
    jump = succ
    while True:
        step = jump[reached]
        step = step[~on[step]]
        if step.size == 0:
            break
        on[step] = True
        reached = np.concatenate([reached, step])
        jump = jump[jump]
    on[m] = False
    on[:m] &= exact | last          # a record not followed by a header may hold the corrupt bytes: dropped
    chain = np.flatnonzero(on[:m])
    return heads[chain], lengths[chain]


def _choose_formats(cands: list[tuple[int, MessageFormat]], banned: set[int]) -> dict[int, Placed]:
    """The first definition of each type id (file order), skipping FMT records known to be off the chain."""
    chosen: dict[int, tuple[int, MessageFormat]] = {}
    for off, f in cands:
        if off not in banned and f.type_id not in chosen:
            chosen[f.type_id] = (off, f)
    return chosen


def attach_units(formats: dict[str, MessageFormat], fmtu: Table | None, unit: Table | None,
                 mult: Table | None) -> dict[str, MessageFormat]:
    """Formats with FMTU/UNIT/MULT units and multipliers (ArduPilot 3.6+) attached per column."""
    if fmtu is None or not fmtu.fmt.has("FmtType", "UnitIds"):
        return formats
    units = dict(zip(unit.num("Id").astype(int).tolist(), unit.text("Label"), strict=True)) if unit else {}
    mults = (dict(zip(mult.num("Id").astype(int).tolist(), mult.num("Mult").tolist(), strict=True))
             if mult else {})
    by_id = {f.type_id: f for f in formats.values()}
    uids = fmtu.text("UnitIds")
    mids = fmtu.text("MultIds") if fmtu.fmt.has("MultIds") else [""] * len(uids)
    for tid, u_s, m_s in zip(np.asarray(fmtu.num("FmtType"), dtype=int).tolist(), uids, mids, strict=False):
        f = by_id.get(tid)
        if f is None:
            continue
        col_units = {c: units[ord(ch)] for c, ch in zip(f.columns, u_s, strict=False)
                     if units.get(ord(ch))}
        col_mults = {c: float(f"{mults[ord(ch)]:.7g}") for c, ch in zip(f.columns, m_s, strict=False)
                     if ord(ch) in mults and ch not in "-?"}
        formats[f.name] = dataclasses.replace(f, units=col_units, mults=col_mults)
    return formats


class _ChainParser:
    """Follows the record chain window by window, keeping only the decoded records of the wanted types.

    Formats found in earlier windows are fixed; a window's own FMT candidates are tried, and one that lies off
    the chain (a bogus FMT inside corrupt bytes) is dropped and the window redone. Records of the wanted types
    are copied out of the window, so memory holds one window plus what the caller asked for.
    """

    def __init__(self, wanted: Collection[str] | None) -> None:
        self.want = None if wanted is None else set(wanted) | set(META_TYPES)
        self.known: dict[int, Placed] = {}
        self.counts: dict[int, int] = {}
        self.parts: dict[int, list[tuple[IntArray, np.ndarray]]] = {}
        self.used = 0
        self.truncated = 0
        self.lost = ""
        self.notes: list[str] = []
        self.complete = 0
        self.trusted = False

    def window(self, buf: np.ndarray, base: int, at_end: bool) -> int:
        """Parse buf (the file from byte `base`); return where the next window starts (the file size at the end).

        When the chain runs on past the window's committed part, the next window trusts its first record."""
        heads = header_candidates(buf)
        cands = [(o + base, f) for o, f in _fmt_candidates(buf, heads) if f.type_id not in self.known]
        banned: set[int] = set()
        data_end = buf.size - _header_prefix(buf) if at_end else buf.size
        cutoff = buf.size if at_end else buf.size - OVERLAP
        for _ in range(8):          # a bogus FMT inside corrupt bytes is dropped and the chain redone
            chosen = {**_choose_formats(cands, banned), **self.known}
            table = np.zeros(256, dtype=np.int64)
            table[FMT_ID] = FMT_LENGTH
            for tid, (_, f) in chosen.items():
                table[tid] = f.length
            lens = table[buf[heads + 2]]
            keep = lens > 0
            offs, lengths = follow_chain(heads[keep], lens[keep], data_end, self.trusted)
            inside = offs < cutoff
            ahead = offs[~inside]
            offs, lengths = offs[inside], lengths[inside]
            new = np.array(sorted(o - base for tid, (o, _) in chosen.items()
                                  if tid not in self.known and o - base < cutoff), dtype=np.int64)
            at = np.minimum(np.searchsorted(offs, new), max(offs.size - 1, 0))
            off_chain = set((new[(offs[at] != new) if offs.size else slice(None)] + base).tolist())
            if not off_chain:
                break
            banned |= off_chain
        self.known.update({tid: pl for tid, pl in chosen.items() if pl[0] - base < cutoff})
        if at_end:
            offs, lengths = self._trim_end(buf, base, offs, lengths)
        self._take(buf, base, offs, lengths)
        if at_end:
            return base + buf.size
        nxt = int(offs[-1] + lengths[-1]) if offs.size else cutoff
        self.trusted = bool(ahead.size) and int(ahead[0]) == nxt
        return base + nxt

    def _trim_end(self, buf: np.ndarray, base: int, offs: IntArray,
                  lengths: IntArray) -> tuple[IntArray, IntArray]:
        """Drop a last record cut off by the end of the file and note the truncation."""
        size = int(buf.size)
        if offs.size and offs[-1] + lengths[-1] > size:
            self.truncated = size - int(offs[-1])
            last = int(buf[offs[-1] + 2])
            name = self.known[last][1].name if last in self.known else "FMT"
            self.lost = f"{a_record(name)}, {self.truncated} of its {int(lengths[-1])} bytes present"
            return offs[:-1], lengths[:-1]
        tail = buf[int(offs[-1] + lengths[-1]) if offs.size else 0:]
        if 0 < tail.size < 3 and tail[0] == HEAD1 and (tail.size == 1 or tail[1] == HEAD2):
            self.truncated = int(tail.size)
            self.lost = f"a record header, {self.truncated} of its 3 bytes present"
        return offs, lengths

    def _take(self, buf: np.ndarray, base: int, offs: IntArray, lengths: IntArray) -> None:
        """Count the chain's records by type and copy out those of the wanted types."""
        self.used += int(lengths.sum())
        self.complete += int(offs.size)
        ids = buf[offs + 2].astype(np.int64)
        order = np.argsort(ids, kind="stable")
        bounds = np.searchsorted(ids[order], np.arange(257))
        for tid in np.flatnonzero(bounds[1:] > bounds[:-1]).tolist():
            at = offs[order[bounds[tid]:bounds[tid + 1]]]
            self.counts[tid] = self.counts.get(tid, 0) + int(at.size)
            f = self.known[tid][1] if tid in self.known else FMT_SELF
            if self.want is None or f.name in self.want:
                width = f.length - 3
                recs = (sliding_window_view(buf, width)[at + 3].copy() if width > 0
                        else np.zeros((at.size, 0), dtype=np.uint8))
                self.parts.setdefault(tid, []).append((at + base, recs))

    def result(self, size: int) -> RawLog:
        """The RawLog of everything parsed so far (call after the last window)."""
        by_id = {tid: f for tid, (_, f) in self.known.items()}
        by_id.setdefault(FMT_ID, FMT_SELF)
        formats = {f.name: f for f in by_id.values()}
        counts: dict[str, int] = {}
        tables: dict[str, Table] = {}
        for tid, n in self.counts.items():
            counts[by_id[tid].name] = counts.get(by_id[tid].name, 0) + n
        for tid in sorted(self.parts):
            parts = self.parts.pop(tid)               # one type at a time: its pieces are freed as it is joined
            f = by_id[tid]
            pos = np.concatenate([p for p, _ in parts])
            raw = np.concatenate([r for _, r in parts])
            del parts
            tables[f.name] = decode_records(raw, pos, f)
        try:
            formats = attach_units(formats, tables.get("FMTU"), tables.get("UNIT"), tables.get("MULT"))
        except (ValueError, KeyError, TypeError, IndexError):
            self.notes.append("ignored FMTU/UNIT/MULT records that do not decode (corrupt data)")
        tables = {k: dataclasses.replace(t, fmt=formats.get(k, t.fmt)) for k, t in tables.items()}
        skipped = size - self.used - self.truncated
        notes = list(self.notes)
        if skipped:
            notes.append(f"skipped {skipped} bytes that are not complete records (corrupt data or padding); "
                         "reading resynchronised on the next message header")
        return RawLog(formats, tables, counts, size, skipped, self.truncated, notes, self.lost)


def decode_records(raw: np.ndarray, pos: IntArray, fmt: MessageFormat) -> Table:
    """A Table from copied record payloads (N, length - 3) uint8 of one type at file offsets `pos`."""
    if fmt.length - 3 <= 0 or pos.size == 0:
        return Table(fmt, pos, {c: np.zeros(0) for c in fmt.columns})
    recs = np.ascontiguousarray(raw).view(fmt.dtype())[:, 0]
    cols: dict[str, np.ndarray] = {}
    for col, name in zip(fmt.columns, recs.dtype.names or (), strict=False):
        cols.setdefault(col, recs[name])
    return Table(fmt, pos, cols)


def parse_buffer(buf: np.ndarray, wanted: Collection[str] | None = None) -> RawLog:
    """Parse a whole binary log held in a uint8 array; decode the types in `wanted` (all when None)."""
    parser = _ChainParser(wanted)
    parser.window(buf, 0, True)
    return parser.result(int(buf.size))


def parse_binary(path: Path, wanted: Collection[str] | None = None, window: int = WINDOW) -> RawLog:
    """Parse a binary DataFlash file window by window (bounded memory); decode the types in `wanted`. The bytes
    parsed are reported per window as the "reading" fraction of `progress.current()`."""
    parser = _ChainParser(wanted)
    hook = current()
    with path.open("rb") as fh:
        size = fh.seek(0, 2)
        buf = np.empty(min(size, window + OVERLAP), dtype=np.uint8)
        pos = 0
        while pos < size or size == 0:
            hook("reading", pos, size)
            fh.seek(pos)
            n = fh.readinto(buf.data)
            at_end = pos + n >= size
            nxt = parser.window(buf[:n], pos, at_end)
            if at_end:
                break
            pos = max(nxt, pos + 1)
    hook("reading", size, size)
    return parser.result(size)

"""Repair of an MCAP bag: keep every chunk whose checksum holds, drop and report the others.

Two faults leave a bag that readers refuse or misread:

* the recorder was killed (SIGKILL, power cut): the file ends inside a chunk or after the last
  complete one, with no summary and no footer (``rosbags`` checks the end magic and refuses it);
* a byte changed inside a chunk of a complete file (a bad disk block, a faulty copy): the
  chunk's CRC-32 over its uncompressed records (``uncompressed_crc``) no longer holds.

:func:`scan_mcap` walks the file record by record, framing each by its own length prefix, and
opens every chunk with ``mcap``'s own ``Chunk.read`` + ``breakup_chunk(validate_crc=True)``. A
chunk that fails (CRC mismatch, undecodable compression, a broken record inside) is dropped and
reported with its offset, size, reason and -- from the message index records that follow it --
how many messages it held; reading goes on at the next record. When a length prefix itself is
broken, reading resumes at the next chunk the file's summary lists (when the summary is
readable), else it stops there, as for a file cut short. Schemas and channels come from the
chunks and from the summary section, so losing the chunk that defined a channel loses only that
chunk's messages.

:func:`repair_bag` then leaves an intact bag untouched (``repaired: false`` with its true message
count), and otherwise writes the kept messages to a complete MCAP file (summary, indexes,
footer) beside the original, keeps the original as ``NAME_0.mcap.orig``, atomically replaces the
MCAP and rewrites ``metadata.yaml`` with the kept counts.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import struct
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any, BinaryIO

import yaml
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Message, MessageIndex, Schema
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, Writer

from peel_msgs_py.atomic import atomic_write_text
from peel_msgs_py.errors import PeelError

from .bag import (
    _LIBRARY,
    _MAGIC,
    DEFAULT_CHUNK_SIZE,
    _DirectFile,
    _dump_metadata,
    _Span,
    mcap_is_complete,
    mcap_path,
    metadata_document,
)

_HEAD = struct.Struct("<BQ")  # record opcode and length


@dataclass
class DroppedChunk:
    """A chunk that failed its check; ``messages`` from its message indexes (None if unknown)."""

    offset: int
    size: int
    reason: str
    messages: int | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"offset": self.offset, "bytes": self.size, "reason": self.reason,
                "messages": self.messages}


@dataclass
class Scan:
    """What one CRC-checked pass over an MCAP file found."""

    size: int
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    messages: list[Message] = field(default_factory=list)
    chunks: int = 0  # chunks kept
    dropped: list[DroppedChunk] = field(default_factory=list)
    footer: bool = False  # the footer record was reached
    good_end: int = 0  # end of the last record read as framed

    @property
    def bytes_dropped(self) -> int:
        tail = max(0, self.size - self.good_end) if not self.footer else 0
        return tail + sum(d.size for d in self.dropped)


def _summary_chunk_offsets(fh: BinaryIO) -> list[int]:
    """Start offsets of the chunks listed in the summary ([] when there is no readable one)."""
    from mcap.reader import make_reader

    try:
        fh.seek(0)
        summary = make_reader(fh).get_summary()
        return sorted(c.chunk_start_offset for c in summary.chunk_indexes) if summary else []
    except Exception:  # no footer or a corrupt summary: nothing to resynchronise on
        return []


def _reason(exc: Exception) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _stream(body: bytes) -> ReadDataStream:
    return ReadDataStream(BytesIO(body))


def _take(scan: Scan, records: list[Any]) -> None:
    for rec in records:
        if isinstance(rec, Schema):
            scan.schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            scan.channels[rec.id] = rec
        elif isinstance(rec, Message):
            scan.messages.append(rec)


def _read_record(scan: Scan, opcode: int, body: bytes, offset: int,
                 last_bad: DroppedChunk | None) -> DroppedChunk | None:
    """Handle one framed record; returns the dropped chunk that later message indexes count."""
    if opcode == Opcode.CHUNK:
        try:
            records = breakup_chunk(Chunk.read(_stream(body)), validate_crc=True)
        except Exception as exc:  # CRC mismatch, bad compression, a broken inner record
            scan.dropped.append(DroppedChunk(offset, _HEAD.size + len(body), _reason(exc)))
            return scan.dropped[-1]
        scan.chunks += 1
        _take(scan, records)
        return None
    if opcode == Opcode.MESSAGE_INDEX:
        if last_bad is not None:
            with contextlib.suppress(Exception):
                n = len(MessageIndex.read(_stream(body)).records)
                last_bad.messages = (last_bad.messages or 0) + n
        return last_bad
    with contextlib.suppress(Exception):  # a broken top-level schema/channel is skipped
        if opcode == Opcode.SCHEMA:
            _take(scan, [Schema.read(_stream(body))])
        elif opcode == Opcode.CHANNEL:
            _take(scan, [Channel.read(_stream(body))])
        elif opcode == Opcode.MESSAGE:
            _take(scan, [Message.read(_stream(body), len(body))])
    return None


def scan_mcap(path: Path) -> Scan:
    """Read every record of ``path``, checking each chunk (module docstring)."""
    with open(path, "rb") as fh:
        scan = Scan(size=os.fstat(fh.fileno()).st_size)
        if fh.read(len(_MAGIC)) != _MAGIC:
            raise PeelError(f"{path} is not an MCAP file (no MCAP magic at its start)")
        listed: list[int] | None = None
        pos = scan.good_end = len(_MAGIC)
        last_bad: DroppedChunk | None = None
        while True:
            head = fh.read(_HEAD.size)
            if len(head) < _HEAD.size:
                break
            opcode, length = _HEAD.unpack(head)
            if length > scan.size - pos - _HEAD.size:  # cut short, or a broken length prefix
                listed = _summary_chunk_offsets(fh) if listed is None else listed
                nxt = next((o for o in listed if o > pos), None)
                if nxt is None:
                    break
                scan.dropped.append(DroppedChunk(pos, nxt - pos, "broken record length; "
                                                 "resumed at the next chunk the summary lists"))
                last_bad = None
                pos = scan.good_end = nxt
                fh.seek(pos)
                continue
            body = fh.read(length)
            last_bad = _read_record(scan, opcode, body, pos, last_bad)
            pos = scan.good_end = pos + _HEAD.size + length
            if opcode == Opcode.FOOTER:
                scan.footer = True
                break
    return scan


@dataclass
class RepairResult:
    """What :func:`repair_bag` found and did."""

    bag: Path
    repaired: bool
    messages: int = 0
    topics: dict[str, int] = field(default_factory=dict)
    original: Path | None = None
    bytes_dropped: int = 0
    chunks: int = 0
    chunks_dropped: list[DroppedChunk] = field(default_factory=list)

    @property
    def messages_dropped(self) -> int | None:
        """Messages in the dropped chunks (None if a dropped chunk's index was lost too)."""
        counts = [d.messages for d in self.chunks_dropped]
        return None if any(c is None for c in counts) else sum(c or 0 for c in counts)

    def as_dict(self) -> dict[str, Any]:
        return {
            "bag": str(self.bag),
            "repaired": self.repaired,
            "messages": self.messages,
            "topics": self.topics,
            "original": str(self.original) if self.original else None,
            "bytes_dropped": self.bytes_dropped,
            "chunks": self.chunks,
            "chunks_dropped": [d.as_dict() for d in self.chunks_dropped],
            "messages_dropped": self.messages_dropped,
        }


def _kept(scan: Scan) -> tuple[list[Message], dict[int, int]]:
    """Messages on a known channel, and the count per channel."""
    counts = dict.fromkeys(scan.channels, 0)
    kept = [m for m in scan.messages if m.channel_id in counts]
    for m in kept:
        counts[m.channel_id] += 1
    return kept, counts


def _write_mcap(tmp: Path, scan: Scan, kept: list[Message], doc: dict[str, Any]) -> None:
    """A complete MCAP file of the kept records."""
    out = _DirectFile(tmp)
    try:
        writer = Writer(out, chunk_size=DEFAULT_CHUNK_SIZE * 4,  # type: ignore[arg-type]
                        compression=CompressionType.LZ4)
        writer.start(profile="ros2", library=_LIBRARY + " repair")
        schema_ids = {sid: writer.register_schema(s.name, s.encoding, s.data)
                      for sid, s in sorted(scan.schemas.items())}
        channel_ids = {cid: writer.register_channel(c.topic, c.message_encoding,
                                                    schema_ids.get(c.schema_id, 0),
                                                    dict(c.metadata))
                       for cid, c in sorted(scan.channels.items())}
        for m in kept:
            writer.add_message(channel_id=channel_ids[m.channel_id], log_time=m.log_time,
                               data=m.data, publish_time=m.publish_time, sequence=m.sequence)
        writer.add_metadata("rosbag2", {
            "serialized_metadata": _dump_metadata(doc["rosbag2_bagfile_information"])})
        writer.finish()
        out.fsync()
    finally:
        out.close()


def _metadata(scan: Scan, counts: dict[int, int], kept: list[Message], file_name: str,
              orig_name: str) -> dict[str, Any]:
    rows = []
    for cid, ch in sorted(scan.channels.items()):
        schema = scan.schemas.get(ch.schema_id)
        qos_text = ch.metadata.get("offered_qos_profiles", "")
        qos = yaml.safe_load(qos_text) if qos_text else []
        rows.append((ch.topic, schema.name if schema else "", qos or [],
                     ch.metadata.get("topic_type_hash", ""), counts[cid]))
    span = _Span()
    for m in kept:
        span.add(m.log_time)
    return metadata_document(file_name, rows, span.start, span.end, {"repaired_from": orig_name})


def repair_bag(path: str | os.PathLike[str]) -> RepairResult:
    """Check a bag's MCAP chunk by chunk and rewrite it without what failed (module docstring).

    Returns ``repaired=False`` with the message count for a bag that is complete and whose every
    chunk holds; raises PeelError when nothing can be kept.
    """
    bag = Path(path)
    if not bag.is_dir():
        raise PeelError(f"bag {bag} is not a directory")
    src = mcap_path(bag)
    scan = scan_mcap(src)
    kept, counts = _kept(scan)
    topics = {ch.topic: counts[cid] for cid, ch in sorted(scan.channels.items())}
    if scan.footer and not scan.dropped and mcap_is_complete(src):
        return RepairResult(bag, repaired=False, messages=len(kept), topics=topics,
                            chunks=scan.chunks)
    if not scan.channels and not kept:
        raise PeelError(f"cannot repair bag {bag}: {src.name} holds no complete chunk")
    orig = src.with_name(src.name + ".orig")
    if orig.exists():
        raise PeelError(f"cannot repair bag {bag}: {orig} already exists")
    doc = _metadata(scan, counts, kept, src.name, orig.name)
    tmp = src.with_name(f".{src.name}.repair")
    tmp.unlink(missing_ok=True)
    _write_mcap(tmp, scan, kept, doc)
    try:
        os.link(src, orig)
    except OSError:
        shutil.copy2(src, orig)
    os.replace(tmp, src)
    atomic_write_text(bag / "metadata.yaml", _dump_metadata(doc))
    return RepairResult(bag, repaired=True, messages=len(kept), topics=topics, original=orig,
                        bytes_dropped=scan.bytes_dropped, chunks=scan.chunks,
                        chunks_dropped=scan.dropped)

"""Incremental MCAP bags in the rosbag2 layout, and the repair of a bag cut short.

A bag is a directory ``NAME/`` holding ``metadata.yaml`` (``rosbag2_bagfile_information``,
version 9, ``storage_identifier: mcap``) and ``NAME_0.mcap``, as ``ros2 bag record -s mcap``
writes it on Jazzy: profile ``ros2``; one schema per message type, encoding ``ros2msg`` with the
full message definition text (dependencies appended after ``====`` separator lines, as rosbag2
does; generated with ``rosbags``' Jazzy typestore); one channel per topic, message encoding
``cdr``, channel metadata ``offered_qos_profiles`` (YAML) and ``topic_type_hash`` (RIHS01);
messages hold the CDR bytes with their 4-byte encapsulation header; a ``rosbag2`` metadata record
with the serialized metadata at close.

Incremental writing (what survives a crash): messages go into a chunk that is written to the
file -- straight to the kernel, no user-space buffer -- as soon as it holds ``chunk_size`` bytes
or is ``flush_interval_s`` old (checked on every write and on :meth:`BagWriter.tick`). A process
killed at any moment therefore leaves every *complete* chunk on disk; what is lost is the open
chunk: at most ``flush_interval_s`` seconds (default 1 s) or ``chunk_size`` bytes (default
64 KiB) of messages, whichever is smaller, plus the index and summary at the end of the file.
``metadata.yaml`` is written at open and rewritten atomically (temp file + ``os.replace``) after
chunk flushes (at most once per ``metadata_interval_s``) and at close.

A file without its summary and footer cannot be opened by ``rosbags`` (it checks the end magic);
:func:`peel_bag.bagrepair.repair_bag` (``peel record --repair BAG``) keeps every
chunk whose CRC holds, drops and reports the others, writes a complete file beside it and
atomically replaces the original, which it keeps as ``NAME_0.mcap.orig``; then it rewrites
``metadata.yaml``.

A write that fails (a full disk: ``ENOSPC``; any ``OSError``) raises :class:`BagWriteError`,
whose message names the bag, the error and the repair command; the writer is then failed: later
writes raise the same error and :meth:`BagWriter.close` only releases the file, which stays cut
short until repaired. :data:`FAIL_AFTER_ENV` (a byte count in the environment) makes the file
refuse, with ``ENOSPC``, any write past that many bytes: the full disk of the tests.
"""

from __future__ import annotations

import contextlib
import errno
import os
import struct
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from mcap.writer import CompressionType, Writer

from peel_msgs_py.atomic import atomic_write_text
from peel_msgs_py.errors import PeelError
from peel_msgs_py.qos import QosSpec

#: rosbag2 metadata version written (Jazzy writes 9).
BAG_VERSION = 9
#: Default chunk size in bytes (uncompressed) and time-based flush interval in s.
DEFAULT_CHUNK_SIZE = 64 * 1024
DEFAULT_FLUSH_INTERVAL_S = 1.0
COMPRESSIONS = {"none": CompressionType.NONE, "lz4": CompressionType.LZ4}
_MAGIC = b"\x89MCAP0\r\n"
_LIBRARY = "peel_msgs_py.bag (mcap-python)"

#: Test hook: the bag file fails with ENOSPC once it would grow past this many bytes.
FAIL_AFTER_ENV = "PEEL_BAG_FAIL_AFTER_BYTES"

_typestore: Any = None


class BagWriteError(PeelError):
    """The bag could not be written (e.g. the disk is full); it is cut short."""


def repair_hint(path: str | os.PathLike[str]) -> str:
    """The command that makes a bag cut short readable again."""
    return f"peel record --repair {path}"


def typestore() -> Any:
    """``rosbags``' ROS 2 Jazzy typestore (message definitions and RIHS01 hashes)."""
    global _typestore
    if _typestore is None:
        from rosbags.typesys import Stores, get_typestore

        _typestore = get_typestore(Stores.ROS2_JAZZY)
    return _typestore


def message_definition(msgtype: str) -> tuple[str, str]:
    """``(ros2msg text, RIHS01 hash)`` of a Jazzy message type; PeelError when unknown."""
    from rosbags.typesys.base import TypesysError

    store = typestore()
    try:
        text, _ = store.generate_msgdef(msgtype, ros_version=2)
        return text, store.hash_rihs01(msgtype)
    except (TypesysError, KeyError):
        raise PeelError(f"unknown message type {msgtype!r}") from None


def qos_yaml(profiles: Sequence[QosSpec | dict[str, Any]]) -> str:
    """``offered_qos_profiles`` channel metadata: the YAML list rosbag2 (v9) writes."""
    items = [p.to_bag() if isinstance(p, QosSpec) else dict(p) for p in profiles]
    return yaml.safe_dump(items, default_flow_style=False, sort_keys=False).strip() if items else ""


def bag_file_name(path: Path) -> str:
    """``NAME_0.mcap`` for bag directory ``NAME`` (rosbag2's naming)."""
    return f"{path.name}_0.mcap"


class _DirectFile:
    """Write-only file with no user-space buffer: every ``write`` reaches the kernel at once.

    ``mcap.Writer`` writes a chunk as a few large ``write`` calls; with this stream, a chunk the
    writer has finished is in the page cache and survives the death of the process.
    """

    def __init__(self, path: Path) -> None:
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        self._pos = 0
        limit = os.environ.get(FAIL_AFTER_ENV, "")
        self._limit = int(limit) if limit.isdigit() else None

    def write(self, data: bytes | bytearray | memoryview) -> int:
        view = memoryview(data)
        if self._limit is not None and self._pos + len(view) > self._limit:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        while view:
            n = os.write(self._fd, view)
            view = view[n:]
            self._pos += n
        return len(data)

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        pass

    def fsync(self) -> None:
        os.fsync(self._fd)

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


@dataclass
class _Topic:
    name: str
    msgtype: str
    channel_id: int
    qos: list[dict[str, Any]]
    rihs01: str
    count: int = 0  # messages in flushed chunks
    pending: int = 0  # messages in the open chunk
    seq: int = 0


@dataclass
class _Span:
    start: int | None = None
    end: int | None = None
    count: int = 0

    def add(self, t: int, n: int = 1) -> None:
        self.start = t if self.start is None else min(self.start, t)
        self.end = t if self.end is None else max(self.end, t)
        self.count += n


def metadata_document(
    relative_file: str,
    topics: Iterable[tuple[str, str, list[dict[str, Any]], str, int]],
    start_ns: int | None,
    end_ns: int | None,
    custom_data: dict[str, str] | None = None,
) -> dict[str, Any]:
    """``metadata.yaml`` content; ``topics`` rows are (name, type, qos dicts, rihs01, count)."""
    rows = list(topics)
    count = sum(r[4] for r in rows)
    start = int(start_ns or 0)
    duration = int(end_ns - start_ns) if (start_ns is not None and end_ns is not None) else 0
    info = {
        "version": BAG_VERSION,
        "storage_identifier": "mcap",
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": count,
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": name,
                    "type": msgtype,
                    "serialization_format": "cdr",
                    "offered_qos_profiles": qos,
                    "type_description_hash": rihs01,
                },
                "message_count": n,
            }
            for name, msgtype, qos, rihs01, n in rows
        ],
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [relative_file],
        "files": [
            {
                "path": relative_file,
                "starting_time": {"nanoseconds_since_epoch": start},
                "duration": {"nanoseconds": duration},
                "message_count": count,
            }
        ],
        "custom_data": dict(custom_data or {}),
        "ros_distro": "jazzy",
    }
    return {"rosbag2_bagfile_information": info}


def _dump_metadata(doc: dict[str, Any]) -> str:
    return yaml.safe_dump(doc, default_flow_style=False, sort_keys=False)


def prepare_bag_dir(path: str | os.PathLike[str]) -> Path:
    """Create the bag directory ``path`` (and its parents); PeelError naming it if impossible.

    The bag must not exist yet (as ``ros2 bag record`` refuses to overwrite a bag).
    """
    path = Path(path)
    if path.exists() or path.is_symlink():
        what = "a directory" if path.is_dir() else "a file"
        raise PeelError(f"cannot write bag {path}: {what} of that name already exists")
    try:
        path.mkdir(parents=True)
    except OSError as exc:
        raise PeelError(f"cannot write bag {path}: {exc.strerror or exc}") from None
    return path


class BagWriter:
    """Write serialized (CDR) messages to a new rosbag2 MCAP bag, incrementally.

    Usage::

        with BagWriter("run1") as bag:
            bag.add_topic("/peel/wrench", "geometry_msgs/msg/WrenchStamped", [STREAM_QOS])
            bag.write("/peel/wrench", cdr_bytes, time.time_ns())
            bag.tick()          # from a timer: time-based chunk flush + metadata refresh

    ``log_time_ns`` is the receive time; times must not go backwards by more than the caller's
    clock does (they are clamped to be non-decreasing, as rosbag2's readers expect).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
        metadata_interval_s: float = 1.0,
        compression: str = "lz4",
        custom_data: dict[str, str] | None = None,
        monotonic: Any = time.monotonic,
    ) -> None:
        if chunk_size < 1:
            raise PeelError(f"bag chunk_size must be >= 1 byte, got {chunk_size}")
        if not flush_interval_s > 0:
            raise PeelError(f"bag flush_interval_s must be > 0, got {flush_interval_s}")
        if compression not in COMPRESSIONS:
            raise PeelError(f"bag compression must be one of {list(COMPRESSIONS)}, got {compression!r}")
        self.path = Path(path)
        self.chunk_size = int(chunk_size)
        self.flush_interval_s = float(flush_interval_s)
        self.metadata_interval_s = float(metadata_interval_s)
        self.compression = compression
        self.custom_data = dict(custom_data or {})
        self._now = monotonic
        self._topics: dict[str, _Topic] = {}
        self._schemas: dict[str, int] = {}
        self._file: _DirectFile | None = None
        self._mcap: Writer | None = None
        self._chunk_bytes = 0
        self._chunk_opened = 0.0
        self._last_meta = -float("inf")
        self._meta_dirty = False
        self._last_log = 0
        self._flushed = _Span()
        self._pending = _Span()
        self.chunks_written = 0
        #: the write error that cut the bag short (:class:`BagWriteError`), once one happened
        self.failure: BagWriteError | None = None
        self._lock = threading.RLock()  # callbacks and timers may run on other threads

    # ------------------------------------------------------------------------------ lifecycle
    def open(self) -> BagWriter:
        """Create the directory and the MCAP file, write the header and ``metadata.yaml``."""
        prepare_bag_dir(self.path)
        self.file_path = self.path / bag_file_name(self.path)
        self.metadata_path = self.path / "metadata.yaml"
        try:
            self._file = _DirectFile(self.file_path)
        except OSError as exc:
            raise PeelError(f"cannot write bag {self.file_path}: {exc.strerror}") from None
        self._mcap = Writer(
            self._file,  # type: ignore[arg-type]
            chunk_size=2**62,  # chunks are cut here, by size and by age
            compression=COMPRESSIONS[self.compression],
        )
        self._mcap.start(profile="ros2", library=_LIBRARY)
        self._write_metadata()
        return self

    def __enter__(self) -> BagWriter:
        return self.open() if self._mcap is None else self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _close_locked(self) -> None:
        """Flush the open chunk, write index, summary, footer and the final ``metadata.yaml``."""
        if self._mcap is None:
            return
        self._flush_chunk()
        doc = self._metadata()
        self._mcap.add_metadata(
            "rosbag2", {"serialized_metadata": _dump_metadata(doc["rosbag2_bagfile_information"])}
        )
        self._mcap.finish()
        assert self._file is not None
        self._file.fsync()
        self._file.close()
        self._mcap = None
        self._file = None
        atomic_write_text(self.metadata_path, _dump_metadata(doc))

    # ------------------------------------------------------------------------------ writing
    @property
    def topics(self) -> list[str]:
        return list(self._topics)

    @property
    def message_count(self) -> int:
        """Messages written so far, including those in the open chunk."""
        return self._flushed.count + self._pending.count

    @property
    def flushed_count(self) -> int:
        """Messages in chunks already on disk (what a crash now would keep)."""
        return self._flushed.count

    def close(self) -> None:
        """Flush the open chunk, write index, summary, footer and the final ``metadata.yaml``;
        a failed writer only releases its file (module docstring)."""
        with self._lock:
            try:
                if self.failure is None:
                    self._guarded(self._close_locked)
            finally:
                if self._file is not None:
                    self._file.close()
                    self._mcap = self._file = None

    def _guarded(self, fn: Any, *args: Any) -> None:
        """``fn(*args)``; an ``OSError`` fails the writer (:class:`BagWriteError`)."""
        if self.failure is not None:
            raise self.failure
        try:
            fn(*args)
        except OSError as exc:
            why = exc.strerror or str(exc)
            code = f" ({errno.errorcode[exc.errno]})" if exc.errno in errno.errorcode else ""
            self.failure = BagWriteError(
                f"writing bag {self.path} failed: {why}{code}; the bag is cut short, repair it "
                f"with: {repair_hint(self.path)}")
            raise self.failure from None

    def add_topic(self, name: str, msgtype: str, qos: Sequence[QosSpec | dict[str, Any]] = (),
                  *, msgdef: str | None = None, rihs01: str | None = None) -> None:
        """Register a topic (a channel), its type's schema on first use, and its offered QoS."""
        with self._lock:
            self._add_topic_locked(name, msgtype, qos, msgdef=msgdef, rihs01=rihs01)

    def write(self, topic: str, data: bytes, log_time_ns: int,
              publish_time_ns: int | None = None) -> None:
        """Append one serialized message received at ``log_time_ns`` (ns since the epoch)."""
        with self._lock:
            self._guarded(self._write_locked, topic, data, log_time_ns, publish_time_ns)

    def tick(self) -> None:
        """Flush the open chunk if it is older than ``flush_interval_s``; refresh metadata."""
        with self._lock:
            self._guarded(self._tick_locked)

    def flush(self) -> None:
        """Write the open chunk now (and refresh ``metadata.yaml``)."""
        with self._lock:
            self._guarded(self._flush_locked)

    # -------------------------------------------------------------------- locked implementations
    def _add_topic_locked(
        self,
        name: str,
        msgtype: str,
        qos: Sequence[QosSpec | dict[str, Any]] = (),
        *,
        msgdef: str | None = None,
        rihs01: str | None = None,
    ) -> None:
        """Register a topic (a channel), its type's schema on first use, and its offered QoS."""
        mcap = self._require_open()
        if name in self._topics:
            if self._topics[name].msgtype != msgtype:
                raise PeelError(f"bag topic {name!r} already has type {self._topics[name].msgtype}")
            return
        if msgdef is None or rihs01 is None:
            msgdef, rihs01 = message_definition(msgtype)
        if msgtype not in self._schemas:
            self._schemas[msgtype] = mcap.register_schema(msgtype, "ros2msg", msgdef.encode())
        qos_dicts = [p.to_bag() if isinstance(p, QosSpec) else dict(p) for p in qos]
        cid = mcap.register_channel(
            name, "cdr", self._schemas[msgtype],
            {"offered_qos_profiles": qos_yaml(qos_dicts), "topic_type_hash": rihs01},
        )
        self._topics[name] = _Topic(name, msgtype, cid, qos_dicts, rihs01)
        self._meta_dirty = True

    def _write_locked(
        self, topic: str, data: bytes, log_time_ns: int, publish_time_ns: int | None = None
    ) -> None:
        """Append one serialized message received at ``log_time_ns`` (ns since the epoch)."""
        mcap = self._require_open()
        try:
            top = self._topics[topic]
        except KeyError:
            raise PeelError(f"bag topic {topic!r} was not added") from None
        t = max(int(log_time_ns), self._last_log)
        self._last_log = t
        if self._pending.count == 0:
            self._chunk_opened = self._now()
        top.seq += 1
        mcap.add_message(
            channel_id=top.channel_id,
            log_time=t,
            data=bytes(data),
            publish_time=t if publish_time_ns is None else int(publish_time_ns),
            sequence=top.seq,
        )
        top.pending += 1
        self._pending.add(t)
        self._chunk_bytes += len(data) + 31  # message record overhead
        if self._chunk_bytes >= self.chunk_size:
            self._flush_chunk()
        else:
            self._tick_locked()

    def _tick_locked(self) -> None:
        """Flush the open chunk if it is older than ``flush_interval_s``; refresh metadata."""
        if self._mcap is None:
            return
        if self._pending.count and self._now() - self._chunk_opened >= self.flush_interval_s:
            self._flush_chunk()
        elif self._meta_dirty and self._now() - self._last_meta >= self.metadata_interval_s:
            self._write_metadata()

    def _flush_locked(self) -> None:
        """Write the open chunk now (and refresh ``metadata.yaml``)."""
        self._require_open()
        self._flush_chunk()
        self._write_metadata()

    # ------------------------------------------------------------------------------ internals
    def _require_open(self) -> Writer:
        if self._mcap is None:
            raise PeelError(f"bag {self.path} is not open")
        return self._mcap

    def _flush_chunk(self) -> None:
        assert self._mcap is not None
        if self._pending.count == 0:
            return
        self._mcap.flush()  # finishes the chunk and writes it (+ message indexes) to the fd
        self.chunks_written += 1
        for top in self._topics.values():
            top.count += top.pending
            top.pending = 0
        assert self._pending.start is not None and self._pending.end is not None
        self._flushed.add(self._pending.start, 0)
        self._flushed.add(self._pending.end, self._pending.count)
        self._pending = _Span()
        self._chunk_bytes = 0
        self._meta_dirty = True
        if self._now() - self._last_meta >= self.metadata_interval_s:
            self._write_metadata()

    def _metadata(self) -> dict[str, Any]:
        rows = [(t.name, t.msgtype, t.qos, t.rihs01, t.count) for t in self._topics.values()]
        return metadata_document(
            bag_file_name(self.path), rows, self._flushed.start, self._flushed.end,
            self.custom_data,
        )

    def _write_metadata(self) -> None:
        atomic_write_text(self.metadata_path, _dump_metadata(self._metadata()))
        self._last_meta = self._now()
        self._meta_dirty = False


# ---------------------------------------------------------------------------------- repair
def mcap_path(bag: Path) -> Path:
    """The bag's MCAP file: from metadata.yaml when readable, else ``NAME_0.mcap``."""
    meta = bag / "metadata.yaml"
    with contextlib.suppress(OSError, yaml.YAMLError, KeyError, TypeError, IndexError):
        info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
        cand = bag / Path(info["relative_file_paths"][0]).name
        if cand.is_file():
            return cand
    cand = bag / bag_file_name(bag)
    if cand.is_file():
        return cand
    found = sorted(bag.glob("*.mcap"))
    if not found:
        raise PeelError(f"bag {bag}: no .mcap file in it")
    return found[0]


def mcap_is_complete(path: Path) -> bool:
    """Whether the file ends with a footer and the closing magic (what rosbags requires)."""
    try:
        size = path.stat().st_size
        if size < 8 + 37:
            return False
        with open(path, "rb") as fh:
            fh.seek(size - 37)
            tail = fh.read(37)
    except OSError:
        return False
    return tail[-8:] == _MAGIC and tail[0] == 0x02 and struct.unpack("<Q", tail[1:9])[0] == 20


"""NACHI-PEEL 1, the line protocol between the bridge and the Nachi controller program.

The contract is docs/nachi_protocol.md; this module is its grammar as code, shared by the bridge
and the emulator:

* :class:`LineSplitter` cuts a byte stream into lines of at most :data:`MAX_LINE` bytes (the
  terminator included); a longer line is discarded up to its ``\\n`` and reported once as
  :data:`OVERSIZE`.
* :func:`parse_controller` / :func:`parse_bridge` turn one line into a message object, or raise
  :class:`LineError` whose ``kind`` is ``malformed`` or ``non_finite`` (strict: printable ASCII,
  exact field counts, decimal numbers ``-?[0-9]+(.[0-9]+)?``, finite).
* Every message object has ``line()``: its encoded form, ``\\n``-terminated bytes.

Units on the line are the paper's (s, mm, mm/s, N); nothing here converts them.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import ClassVar

from peel_msgs_py.wire import CMD_MAX_MMPS, CMD_MIN_MMPS

PROTOCOL = "NACHI-PEEL"
VERSION = 1
DEFAULT_PORT = 48100
#: Longest line in bytes, terminator included.
MAX_LINE = 256
#: Controller time between samples, s (section 4.2: 100 ms).
SAMPLE_PERIOD_S = 0.1
#: No ``V`` (accepted or refused) for this long (controller time, s) during a task trips the watchdog.
WATCHDOG_S = 1.0
#: The controller's accepted command range, mm/s.
V_MIN_MMPS, V_MAX_MMPS = CMD_MIN_MMPS, CMD_MAX_MMPS
#: Reasons of ``DONE``.
DONE_REASONS = ("reached", "stopped", "timeout", "alarm")

# ERR and ALARM codes (docs/nachi_protocol.md, "Error and alarm codes")
ERR_SYNTAX = 11
ERR_NUMBER = 12
ERR_TOO_LONG = 13
ERR_RANGE = 21
ERR_NO_TASK = 22
ERR_TASK_RUNNING = 23
ERR_BUSY = 31
ALARM_WATCHDOG = 10
ALARM_FORCE = 20

#: Kinds of bad lines (counted separately by the bridge).
OVERSIZE, MALFORMED, NON_FINITE = "oversize", "malformed", "non_finite"
BAD_KINDS = (OVERSIZE, MALFORMED, NON_FINITE)

_NUMBER = re.compile(r"-?[0-9]+(?:\.[0-9]+)?\Z")
_NON_FINITE = re.compile(r"[+-]?(?:nan|inf|infinity)\Z", re.IGNORECASE)
_INTEGER = re.compile(r"[0-9]{1,18}\Z")
TOKEN = re.compile(r"[A-Za-z0-9._:-]+\Z")


class LineError(ValueError):
    """A line that breaks the grammar; ``kind`` is one of :data:`BAD_KINDS`."""

    def __init__(self, kind: str, detail: str) -> None:
        super().__init__(f"{kind}: {detail}")
        self.kind = kind
        self.detail = detail


# ------------------------------------------------------------------------------- line splitting
class LineSplitter:
    """Bytes in, lines out, at most :data:`MAX_LINE` bytes each (terminator included).

    :meth:`pop` returns the next complete line (bytes, terminator included), :data:`OVERSIZE`
    once for a line that grew past the limit (its bytes up to the next ``\\n`` are dropped),
    or ``None`` when no complete line is buffered.
    """

    def __init__(self, max_line: int = MAX_LINE) -> None:
        self.max_line = max_line
        self._buf = bytearray()
        self._skipping = False

    def feed(self, data: bytes) -> None:
        self._buf += data

    def pop(self) -> bytes | str | None:
        while True:
            nl = self._buf.find(b"\n")
            if self._skipping:  # the rest of an oversize line
                if nl < 0:
                    self._buf.clear()
                    return None
                del self._buf[: nl + 1]
                self._skipping = False
                continue
            if nl < 0:
                if len(self._buf) >= self.max_line:  # no room left for the terminator
                    self._buf.clear()
                    self._skipping = True
                    return OVERSIZE
                return None
            line = bytes(self._buf[: nl + 1])
            del self._buf[: nl + 1]
            return OVERSIZE if len(line) > self.max_line else line


# ------------------------------------------------------------------------------------ fields
def _fields(raw: bytes) -> tuple[str, list[str]]:
    """The line's text (terminator removed) and its space-separated fields."""
    body = raw[:-1] if raw.endswith(b"\n") else raw
    if body.endswith(b"\r"):
        body = body[:-1]
    bad = next((b for b in body if not 0x20 <= b <= 0x7E), None)
    if bad is not None:
        raise LineError(MALFORMED, f"byte 0x{bad:02x} is not printable ASCII")
    text = body.decode("ascii").strip(" ")
    fields = [f for f in text.split(" ") if f]
    if not fields:
        raise LineError(MALFORMED, "empty line")
    return text, fields


def number(field: str, name: str) -> float:
    """A decimal field as a finite float; :class:`LineError` naming the field otherwise."""
    if _NUMBER.match(field):
        value = float(field)
        if math.isfinite(value):
            return value
        raise LineError(NON_FINITE, f"{name} = {field[:20]} overflows")
    if _NON_FINITE.match(field):
        raise LineError(NON_FINITE, f"{name} = {field}")
    raise LineError(MALFORMED, f"{name} = {field[:20]!r} is not a decimal number")


def integer(field: str, name: str) -> int:
    if not _INTEGER.match(field):
        raise LineError(MALFORMED, f"{name} = {field[:20]!r} is not an integer")
    return int(field)


def _count(fields: list[str], n: int) -> None:
    if len(fields) != n:
        raise LineError(MALFORMED, f"{fields[0]} takes {n - 1} fields, got {len(fields) - 1}")


def _rest(text: str, skip: int) -> str:
    """The text after the first ``skip`` fields (free text of ERR / ALARM)."""
    parts = text.split(None, skip)
    return parts[skip] if len(parts) > skip else ""


def _fmt(x: float, digits: int) -> str:
    if not math.isfinite(x):
        raise ValueError(f"NACHI-PEEL numbers must be finite, got {x!r}")
    return f"{x:.{digits}f}"


# ------------------------------------------------------------------ controller -> bridge messages
@dataclass(frozen=True)
class Hello:
    protocol: str
    version: int
    controller_id: str

    def line(self) -> bytes:
        return f"HELLO {self.protocol} {self.version} {self.controller_id}\n".encode()


@dataclass(frozen=True)
class OkStart:
    task_id: int

    def line(self) -> bytes:
        return f"OK START {self.task_id}\n".encode()


@dataclass(frozen=True)
class OkStop:
    def line(self) -> bytes:
        return b"OK STOP\n"


@dataclass(frozen=True)
class Sample:
    """``S``: t (s from the task's start), q (mm), v (mm/s), fx = F_RX and fz = F_RZ (N)."""

    t: float
    q: float
    v: float
    fx: float
    fz: float

    def line(self) -> bytes:
        return (f"S {_fmt(self.t, 3)} {_fmt(self.q, 4)} {_fmt(self.v, 4)} {_fmt(self.fx, 3)} "
                f"{_fmt(self.fz, 3)}\n").encode()


@dataclass(frozen=True)
class Done:
    t: float
    reason: str

    def line(self) -> bytes:
        return f"DONE {_fmt(self.t, 3)} {self.reason}\n".encode()


@dataclass(frozen=True)
class Alarm:
    code: int
    text: str

    def line(self) -> bytes:
        return f"ALARM {self.code} {self.text}\n".encode()


@dataclass(frozen=True)
class Err:
    code: int
    text: str

    def line(self) -> bytes:
        return f"ERR {self.code} {self.text}\n".encode()


@dataclass(frozen=True)
class Pong:
    t: float

    def line(self) -> bytes:
        return f"PONG {_fmt(self.t, 3)}\n".encode()


# ------------------------------------------------------------------ bridge -> controller messages
@dataclass(frozen=True)
class Start:
    def line(self) -> bytes:
        return b"START\n"


@dataclass(frozen=True)
class Velocity:
    """``V``: commanded blade speed along the peel axis, mm/s."""

    u: float

    def line(self) -> bytes:
        return f"V {_fmt(self.u, 4)}\n".encode()


@dataclass(frozen=True)
class Stop:
    def line(self) -> bytes:
        return b"STOP\n"


@dataclass(frozen=True)
class Ping:
    def line(self) -> bytes:
        return b"PING\n"


ControllerMessage = Hello | OkStart | OkStop | Sample | Done | Alarm | Err | Pong
BridgeMessage = Start | Velocity | Stop | Ping


# ------------------------------------------------------------------------------------ parsing
class _Parser:
    """Dispatch on the first field; subclasses list their keywords."""

    keywords: ClassVar[dict[str, str]]

    def __call__(self, raw: bytes) -> object:
        text, f = _fields(raw)
        method = self.keywords.get(f[0])
        if method is None:
            raise LineError(MALFORMED, f"unknown keyword {f[0][:20]!r}")
        return getattr(self, method)(text, f)


class _ControllerParser(_Parser):
    keywords: ClassVar[dict[str, str]] = {
        "S": "sample", "HELLO": "hello", "OK": "ok", "DONE": "done", "ALARM": "alarm",
        "ERR": "err", "PONG": "pong"}

    def sample(self, text: str, f: list[str]) -> Sample:
        _count(f, 6)
        names = ("t", "q", "v", "fx", "fz")
        return Sample(*(number(x, n) for x, n in zip(f[1:], names, strict=True)))

    def hello(self, text: str, f: list[str]) -> Hello:
        _count(f, 4)
        if not TOKEN.match(f[3]):
            raise LineError(MALFORMED, f"controller id {f[3][:20]!r} is not one token")
        return Hello(f[1], integer(f[2], "version"), f[3])

    def ok(self, text: str, f: list[str]) -> OkStart | OkStop:
        if len(f) == 3 and f[1] == "START":
            return OkStart(integer(f[2], "task_id"))
        if len(f) == 2 and f[1] == "STOP":
            return OkStop()
        raise LineError(MALFORMED, "OK must be 'OK START <task_id>' or 'OK STOP'")

    def done(self, text: str, f: list[str]) -> Done:
        _count(f, 3)
        if f[2] not in DONE_REASONS:
            raise LineError(MALFORMED, f"DONE reason {f[2][:20]!r} is not one of {DONE_REASONS}")
        return Done(number(f[1], "t"), f[2])

    def alarm(self, text: str, f: list[str]) -> Alarm:
        if len(f) < 3:
            raise LineError(MALFORMED, "ALARM takes a code and a text")
        return Alarm(integer(f[1], "code"), _rest(text, 2))

    def err(self, text: str, f: list[str]) -> Err:
        if len(f) < 3:
            raise LineError(MALFORMED, "ERR takes a code and a text")
        return Err(integer(f[1], "code"), _rest(text, 2))

    def pong(self, text: str, f: list[str]) -> Pong:
        _count(f, 2)
        return Pong(number(f[1], "t"))


class _BridgeParser(_Parser):
    keywords: ClassVar[dict[str, str]] = {
        "V": "velocity", "START": "start", "STOP": "stop", "PING": "ping"}

    def velocity(self, text: str, f: list[str]) -> Velocity:
        _count(f, 2)
        return Velocity(number(f[1], "u"))

    def start(self, text: str, f: list[str]) -> Start:
        _count(f, 1)
        return Start()

    def stop(self, text: str, f: list[str]) -> Stop:
        _count(f, 1)
        return Stop()

    def ping(self, text: str, f: list[str]) -> Ping:
        _count(f, 1)
        return Ping()


_CONTROLLER = _ControllerParser()
_BRIDGE = _BridgeParser()


def parse_controller(raw: bytes) -> ControllerMessage:
    """One controller line (bytes, terminator optional) -> message; :class:`LineError` if bad."""
    return _CONTROLLER(raw)  # type: ignore[return-value]


def parse_bridge(raw: bytes) -> BridgeMessage:
    """One bridge line (bytes, terminator optional) -> message; :class:`LineError` if bad."""
    return _BRIDGE(raw)  # type: ignore[return-value]


def preview(raw: bytes | str, limit: int = 60) -> str:
    """A loggable, bounded rendering of a received line."""
    if isinstance(raw, str):
        return raw
    text = repr(raw[:limit])
    return text + ("..." if len(raw) > limit else "")

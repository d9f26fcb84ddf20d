"""One TCP connection to the controller, and the backoff between attempts (docs/nachi.md).

:meth:`Connection.open` connects, reads ``HELLO`` within the hello timeout and checks the
protocol name and version; every failure is a :class:`LinkError` whose message says what went
wrong (refused, timed out, no HELLO, another protocol version). After that the connection sends
whole lines under a lock (the bridge thread's ``STOP`` and the node's ``V`` never interleave)
and hands out received lines one at a time with the time their bytes arrived, so the bridge can
act on a line before it parses the next.
"""

from __future__ import annotations

import contextlib
import select
import socket
import threading
import time
from dataclasses import dataclass
from typing import Any

from . import protocol as p


class LinkError(Exception):
    """The link failed or the peer broke the handshake; the message says how."""


class Backoff:
    """Reconnect delays: ``initial``, then times ``factor`` per failure, at most ``maximum``."""

    def __init__(self, initial: float, maximum: float, factor: float) -> None:
        self.initial, self.maximum, self.factor = initial, maximum, factor
        self._next = initial

    def next(self) -> float:
        delay = self._next
        self._next = min(self._next * self.factor, self.maximum)
        return delay

    def reset(self) -> None:
        self._next = self.initial


@dataclass(frozen=True)
class Received:
    """One received line (or :data:`~.protocol.OVERSIZE`) and when its last bytes arrived
    (``time.perf_counter()`` right after the ``recv`` that completed it)."""

    raw: bytes | str
    at: float


class Connection:
    """An open, greeted connection to a NACHI-PEEL 1 controller."""

    def __init__(self, sock: socket.socket, peer: str, hello: p.Hello,
                 splitter: p.LineSplitter) -> None:
        self.sock = sock
        self.peer = peer
        self.hello = hello
        self._splitter = splitter
        self._send_lock = threading.Lock()
        self._last_recv = time.perf_counter()

    @classmethod
    def open(cls, host: str, port: int, connect_timeout_s: float,
             hello_timeout_s: float) -> Connection:
        """Connect and read the greeting; :class:`LinkError` saying why not."""
        peer = f"{host}:{port}"
        try:
            sock = socket.create_connection((host, port), timeout=connect_timeout_s)
        except OSError as exc:
            raise LinkError(f"cannot connect to {peer}: {exc.strerror or exc}") from None
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.settimeout(max(connect_timeout_s, 1.0))  # bounds sendall to a stuck peer
            splitter = p.LineSplitter()
            hello = _read_hello(sock, splitter, peer, hello_timeout_s)
        except BaseException:
            sock.close()
            raise
        return cls(sock, peer, hello, splitter)

    def send(self, msg: Any) -> float:
        """Send one message; returns ``time.perf_counter()`` once it is handed to the kernel."""
        data = msg.line()
        with self._send_lock:
            try:
                self.sock.sendall(data)
            except OSError as exc:
                raise LinkError(f"send to {self.peer} failed: {exc.strerror or exc}") from None
            return time.perf_counter()

    def receive(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for bytes; True when some arrived. :class:`LinkError` when
        the controller closed the connection or it broke."""
        try:
            readable, _, _ = select.select([self.sock], [], [], max(0.0, timeout_s))
            if not readable:
                return False
            data = self.sock.recv(65536)
        except (OSError, ValueError) as exc:
            raise LinkError(f"connection to {self.peer} broke: {exc}") from None
        self._last_recv = time.perf_counter()
        if not data:
            raise LinkError(f"controller at {self.peer} closed the connection")
        self._splitter.feed(data)
        return True

    def pop(self) -> Received | None:
        """The next buffered line, or None."""
        raw = self._splitter.pop()
        return None if raw is None else Received(raw, self._last_recv)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()


def _read_hello(sock: socket.socket, splitter: p.LineSplitter, peer: str,
                timeout_s: float) -> p.Hello:
    deadline = time.monotonic() + timeout_s
    while (raw := splitter.pop()) is None:
        left = deadline - time.monotonic()
        if left <= 0:
            raise LinkError(f"no HELLO from {peer} within {timeout_s:g} s")
        readable, _, _ = select.select([sock], [], [], left)
        if not readable:
            continue
        try:
            data = sock.recv(4096)
        except OSError as exc:
            raise LinkError(f"connection to {peer} broke before HELLO: {exc}") from None
        if not data:
            raise LinkError(f"controller at {peer} closed the connection before HELLO")
        splitter.feed(data)
    try:
        msg = p.parse_controller(raw) if raw != p.OVERSIZE else None  # type: ignore[arg-type]
    except p.LineError as exc:
        raise LinkError(f"bad greeting from {peer}: {exc}") from None
    if isinstance(msg, p.Err):
        raise LinkError(f"controller at {peer} refused the connection: ERR {msg.code} {msg.text}")
    if not isinstance(msg, p.Hello):
        raise LinkError(f"controller at {peer} did not start with HELLO: {p.preview(raw)}")
    if msg.protocol != p.PROTOCOL or msg.version != p.VERSION:
        raise LinkError(f"controller at {peer} speaks {msg.protocol} {msg.version}, this bridge "
                        f"speaks {p.PROTOCOL} {p.VERSION}")
    return msg

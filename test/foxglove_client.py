"""A Foxglove WebSocket protocol client on the standard library alone (RFC 6455 framing), for the
live view's tests: the client side of ``foxglove.websocket.v1`` that Foxglove's app speaks.

The server sends JSON text frames (``serverInfo``, ``advertise``, ...) and binary frames; a
``messageData`` binary frame is opcode 0x01, the subscription id (uint32 LE), the log time
(uint64 LE, ns) and the message (here JSON). The client subscribes with
``{"op": "subscribe", "subscriptions": [{"id", "channelId"}]}``; frames it sends are masked.
"""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
import time
from typing import Any

SUBPROTOCOLS = ("foxglove.websocket.v1", "foxglove.sdk.v1")
TEXT, BINARY, CLOSE, PING, PONG = 0x1, 0x2, 0x8, 0x9, 0xA
MESSAGE_DATA = 0x01


class FoxgloveClient:
    """One connection; :meth:`recv` returns ("text", dict) or ("binary", bytes)."""

    def __init__(self, host: str, port: int, timeout_s: float = 5.0) -> None:
        self.sock = socket.create_connection((host, port), timeout=timeout_s)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                           f"Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: {', '.join(SUBPROTOCOLS)}"
                           "\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(1)
            if not chunk:
                raise ConnectionError("closed during the handshake")
            head += chunk
        lines = head.decode(errors="replace").split("\r\n")
        if " 101 " not in lines[0]:
            raise ConnectionError(f"handshake refused: {lines[0]}")
        self.headers = {k.strip().lower(): v.strip() for k, _, v in
                        (line.partition(":") for line in lines[1:] if line)}

    def _exact(self, n: int) -> bytes:
        out = b""
        while len(out) < n:
            chunk = self.sock.recv(n - len(out))
            if not chunk:
                raise ConnectionError("connection closed")
            out += chunk
        return out

    def _frame(self) -> tuple[int, bytes]:
        b0, b1 = self._exact(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", self._exact(2))[0]
        elif n == 127:
            n = struct.unpack(">Q", self._exact(8))[0]
        mask = self._exact(4) if b1 & 0x80 else b""
        data = self._exact(n)
        if mask:
            data = bytes(c ^ mask[i % 4] for i, c in enumerate(data))
        return b0, data

    def send(self, payload: bytes, opcode: int = TEXT) -> None:
        mask = os.urandom(4)
        n = len(payload)
        head = bytes([0x80 | opcode])
        if n < 126:
            head += bytes([0x80 | n])
        elif n < 1 << 16:
            head += bytes([0x80 | 126]) + struct.pack(">H", n)
        else:
            head += bytes([0x80 | 127]) + struct.pack(">Q", n)
        self.sock.sendall(head + mask + bytes(c ^ mask[i % 4] for i, c in enumerate(payload)))

    def recv(self) -> tuple[str, Any]:
        """The next whole message (fragments joined; pings answered)."""
        parts: list[bytes] = []
        kind = None
        while True:
            b0, data = self._frame()
            opcode = b0 & 0x0F
            if opcode == PING:
                self.send(data, PONG)
                continue
            if opcode == CLOSE:
                raise ConnectionError("closed by the server")
            if opcode in (TEXT, BINARY):
                kind = opcode
            parts.append(data)
            if b0 & 0x80:
                break
        data = b"".join(parts)
        return ("text", json.loads(data)) if kind == TEXT else ("binary", data)

    def subscribe(self, channel_ids: dict[int, int]) -> None:
        """``{subscription id: channel id}``."""
        subs = [{"id": sid, "channelId": cid} for sid, cid in channel_ids.items()]
        self.send(json.dumps({"op": "subscribe", "subscriptions": subs}).encode())

    def close(self) -> None:
        self.sock.close()


def message_data(data: bytes) -> tuple[int, int, bytes]:
    """A ``messageData`` frame: (subscription id, log time ns, message bytes)."""
    if data[0] != MESSAGE_DATA:
        raise ValueError(f"not messageData: opcode {data[0]:#x}")
    sid, log_ns = struct.unpack_from("<IQ", data, 1)
    return sid, log_ns, data[13:]


def connect(host: str, port: int, timeout_s: float) -> FoxgloveClient:
    """Connect, retrying while the server is not up yet (``timeout_s`` in all)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return FoxgloveClient(host, port)
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)

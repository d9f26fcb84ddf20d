"""The controller emulator: NACHI-PEEL 1 over TCP around :class:`~.robot.Robot` (the plant).

``ControllerEmulator(options).start()`` listens on ``options.host:options.port`` (127.0.0.1 and
48100 by default; port 0 picks a free one, see :attr:`ControllerEmulator.port`) and serves one
client at a time from one thread:

* on accept it says ``HELLO NACHI-PEEL 1 <controller_id>``; a second client gets ``ERR 31`` and
  is closed;
* commands are answered at once (:meth:`.robot.Robot.command`);
* while a task runs, one sample period of the plant is integrated every ``0.1 / speed`` s of wall
  time on a fixed schedule (``speed`` = X times real time; every ``t`` on the line stays
  controller time), and its lines go out;
* a lost connection stops the robot.

The faults of :mod:`.faults` are applied here, on the way out. Every event (connection, task
start, accepted and refused ``V``, ``STOP`` with the sample it answered, alarms, faults fired)
is kept in :attr:`ControllerEmulator.events` for tests and benchmarks.
"""

from __future__ import annotations

import contextlib
import select
import socket
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from peel_msgs_py.errors import PeelError
from peel_nachi_bridge import protocol as p

from .faults import CONNECTION_KINDS, Fault
from .robot import Robot


@dataclass(frozen=True)
class EmulatorOptions:
    host: str = "127.0.0.1"
    port: int = p.DEFAULT_PORT
    source: str = "sim"
    speed: float = 1.0
    seed: int = 0
    controller_id: str = "EMU-MZ04"
    force_alarm_n: float = 25.0
    faults: tuple[Fault, ...] = ()

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise PeelError(f"emulator port {self.port} is not in 0..65535")
        if not (self.speed > 0 and self.speed < float("inf")):
            raise PeelError(f"emulator speed must be a finite number > 0, got {self.speed!r}")
        if self.source not in ("sim", "plant"):
            raise PeelError(f"emulator plant must be sim or plant, got {self.source!r}")
        if not self.force_alarm_n > 0:
            raise PeelError(f"emulator force alarm must be > 0 N, got {self.force_alarm_n!r}")


@dataclass
class Event:
    kind: str
    wall: float
    data: dict[str, Any] = field(default_factory=dict)


class _Session:
    """One accepted connection and what the faults do to it."""

    def __init__(self, sock: socket.socket, index: int) -> None:
        self.sock = sock
        self.index = index
        self.splitter = p.LineSplitter()
        self.mute = False  # no-hello: say nothing, answer nothing
        self.last_sample_wall = 0.0


class ControllerEmulator:
    """The emulated Nachi controller (module docstring)."""

    def __init__(self, options: EmulatorOptions, *, robot: Robot | None = None,
                 log: Callable[[str], None] | None = None) -> None:
        self.opts = options
        self.robot = robot if robot is not None else Robot(
            source=options.source, seed=options.seed, force_alarm_n=options.force_alarm_n)
        self.log = log or (lambda text: print(f"peel nachi-emulator: {text}", file=sys.stderr,
                                              flush=True))
        self.events: list[Event] = []
        self._cond = threading.Condition()
        self._pending = list(options.faults)
        self._listener: socket.socket | None = None
        self._client: _Session | None = None
        self._accepted = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._t_wall0 = time.monotonic()
        self._period = self.robot.dt / options.speed
        self._next_tick = 0.0
        self._tick_wall = 0.0  # wall time of the last sample period's end
        self._stall_until_t = -1.0
        self._corrupt: dict[str, int] = {}  # nan / inf: samples left to corrupt

    # ------------------------------------------------------------------ lifecycle
    def bind(self) -> ControllerEmulator:
        """Listen (port 0: any free port); a taken port is a :class:`PeelError` naming it."""
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((self.opts.host, self.opts.port))
        except OSError as exc:
            sock.close()
            raise PeelError(f"cannot listen on {self.opts.host}:{self.opts.port}: "
                            f"{exc.strerror or exc}") from None
        sock.listen(4)
        self._listener = sock
        return self

    @property
    def port(self) -> int:
        assert self._listener is not None, "bind() first"
        return int(self._listener.getsockname()[1])

    def start(self) -> ControllerEmulator:
        """Bind (if not yet) and serve from a daemon thread."""
        if self._listener is None:
            self.bind()
        self._thread = threading.Thread(target=self.serve, name="nachi-emulator", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._drop_client("emulator closing")
        if self._listener is not None:
            self._listener.close()
        self.robot.close()

    def __enter__(self) -> ControllerEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ events
    def record(self, kind: str, **data: Any) -> None:
        with self._cond:
            self.events.append(Event(kind, time.monotonic(), data))
            self._cond.notify_all()

    def wait_for(self, kind: str, timeout: float, count: int = 1) -> list[Event]:
        """Block until ``count`` events of ``kind`` were recorded (or ``timeout`` s passed)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                found = [e for e in self.events if e.kind == kind]
                left = deadline - time.monotonic()
                if len(found) >= count or left <= 0:
                    return found
                self._cond.wait(left)

    def of_kind(self, kind: str) -> list[Event]:
        with self._cond:
            return [e for e in self.events if e.kind == kind]

    # ------------------------------------------------------------------ the serving loop
    def serve(self) -> None:
        """Serve until :meth:`close` (or SIGINT in the CLI)."""
        assert self._listener is not None, "bind() first"
        self.log(f"listening on {self.opts.host}:{self.port} (plant {self.opts.source}, "
                 f"speed {self.opts.speed:g}x, seed {self.opts.seed})")
        while not self._stop.is_set():
            self._poll(self._timeout())
            if self.robot.running and time.monotonic() >= self._next_tick:
                self._tick()

    def _timeout(self) -> float:
        if not self.robot.running:
            return 0.05
        return min(0.05, max(0.0, self._next_tick - time.monotonic()))

    def _poll(self, timeout: float) -> None:
        assert self._listener is not None
        socks = [self._listener] + ([self._client.sock] if self._client else [])
        readable, _, _ = select.select(socks, [], [], timeout)
        if self._listener in readable:
            self._accept()
        if self._client is not None and self._client.sock in readable:
            self._receive(self._client)

    def _accept(self) -> None:
        assert self._listener is not None
        sock, addr = self._listener.accept()
        if self._client is not None:
            with contextlib.suppress(OSError):
                sock.sendall(p.Err(p.ERR_BUSY, "busy: another client is connected").line())
            sock.close()
            self.record("refused_client", addr=str(addr))
            return
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(5.0)
        session = _Session(sock, self._accepted)
        self._accepted += 1
        self._client = session
        self.record("connect", conn=session.index)
        self.log(f"connection {session.index} from {addr[0]}:{addr[1]}")
        greet = p.Hello(p.PROTOCOL, p.VERSION, self.opts.controller_id)
        for fault in self._pending:
            if fault.kind in CONNECTION_KINDS and fault.matches_conn(session.index):
                self.record("fault", fault=fault.kind, conn=session.index)
                if fault.kind == "no-hello":
                    session.mute = True
                else:
                    greet = p.Hello(p.PROTOCOL, fault.version, self.opts.controller_id)
        if not session.mute:
            self._send(session, [greet])

    def _receive(self, session: _Session) -> None:
        try:
            data = session.sock.recv(4096)
        except OSError:
            data = b""
        if not data:
            self._drop_client("the bridge closed the connection")
            return
        if session.mute:
            return
        session.splitter.feed(data)
        while self._client is session and (raw := session.splitter.pop()) is not None:
            self._send(session, self._answer(raw))

    def _answer(self, raw: bytes | str) -> list[Any]:
        if raw == p.OVERSIZE:
            return [p.Err(p.ERR_TOO_LONG, "line too long")]
        try:
            msg = p.parse_bridge(raw)  # type: ignore[arg-type]
        except p.LineError as exc:
            code = p.ERR_SYNTAX if exc.kind == p.MALFORMED else p.ERR_NUMBER
            return [p.Err(code, f"{'syntax' if code == p.ERR_SYNTAX else 'number'}: {exc.detail}")]
        now_t = self._task_time()
        was_running, task = self.robot.running, self.robot.task
        out = self.robot.command(msg, now_t)
        self._note_command(msg, out, was_running, task, now_t)
        if isinstance(msg, p.Start) and not was_running and self.robot.running:
            self._begin_task()
        return out

    def _note_command(self, msg: Any, out: list[Any], was_running: bool, task: int,
                      now_t: float) -> None:
        err = next((m for m in out if isinstance(m, p.Err)), None)
        if isinstance(msg, p.Velocity):
            self.record("refused_v" if err else "v", u=msg.u, t=now_t, task=task,
                        code=err.code if err else None)
        elif isinstance(msg, p.Stop) and was_running:
            since = time.monotonic() - self._client.last_sample_wall if self._client else None
            self.record("stop", task=task, t=now_t, sample_t=self.robot.t, since_sample_s=since)
            self.log(f"task id {task}: STOP at t={now_t:.3f} s")
        elif isinstance(msg, p.Start) and not err:
            self.record("start", task=self.robot.task)
            self.log(f"task id {self.robot.task}: START")

    def _begin_task(self) -> None:
        now = time.monotonic()
        self._tick_wall = now
        self._next_tick = now + self._period
        self._stall_until_t = -1.0
        self._corrupt.clear()
        if self._client is not None:
            self._client.last_sample_wall = now

    def _task_time(self) -> float:
        """Controller time now: the task's time during a task, else the controller's clock."""
        now = time.monotonic()
        if not self.robot.running:
            return (now - self._t_wall0) * self.opts.speed
        return self.robot.t + min(now - self._tick_wall, self._period) * self.opts.speed

    # ------------------------------------------------------------------ samples and faults
    def _tick(self) -> None:
        self._tick_wall = time.monotonic()
        self._next_tick += self._period
        task = self.robot.task
        out = self.robot.tick()
        for m in out:
            if isinstance(m, p.Alarm):
                self.record("alarm", task=task, code=m.code, text=m.text, t=self.robot.t)
                self.log(f"task id {task}: ALARM {m.code} {m.text} at t={self.robot.t:.1f} s")
            elif isinstance(m, p.Done):
                self.record("done", task=task, reason=m.reason, t=m.t)
        session = self._client
        if session is None or session.mute:
            return
        lines = self._apply_faults(session, out, task)
        if lines is not None:
            self._send(session, lines)

    def _due(self, kinds: tuple[str, ...], task: int, t: float) -> Fault | None:
        """The first pending fault of ``kinds`` due at task time ``t``; it fires (once)."""
        for fault in self._pending:
            if fault.kind in kinds and fault.matches_task(task) and t >= fault.t - 1e-9:
                self._pending.remove(fault)
                self.record("fault", fault=fault.kind, task=task, t=t)
                self.log(f"task id {task}: fault {fault.kind} at t={t:.1f} s")
                return fault
        return None

    def _apply_faults(self, session: _Session, out: list[Any], task: int) -> list[Any] | None:
        sample = out[0]
        t = sample.t
        if self._due(("drop",), task, t):
            self.robot.abort()
            self._drop_client(f"fault: connection dropped at t={t:.1f} s")
            return None
        lines: list[Any] = []
        fault = self._due(("garbage", "oversize"), task, t)
        if fault is not None:
            lines += _junk(fault)
        fault = self._due(("nan", "inf"), task, t)
        if fault is not None:
            self._corrupt[fault.kind] = fault.n
        fault = self._due(("stall",), task, t)
        if fault is not None:
            self._stall_until_t = t + fault.s
        fault = self._due(("spike",), task, t)
        if fault is not None:
            sample = p.Sample(sample.t, sample.q, sample.v, fault.f, sample.fz)
        for kind, left in list(self._corrupt.items()):
            if left > 0:
                sample = _Corrupt(sample, kind)
                self._corrupt[kind] = left - 1
        if t < self._stall_until_t - 1e-9:
            return out[1:] or None  # the sample is lost; the end still goes out
        return [*lines, sample, *out[1:]]

    # ------------------------------------------------------------------ sending
    def _send(self, session: _Session, msgs: list[Any]) -> None:
        if not msgs or self._client is not session:
            return
        data = b"".join(m if isinstance(m, bytes) else m.line() for m in msgs)
        try:
            session.sock.sendall(data)
        except OSError as exc:
            self._drop_client(f"send failed: {exc}")
            return
        if any(isinstance(m, (p.Sample, _Corrupt)) for m in msgs):
            session.last_sample_wall = time.monotonic()

    def _drop_client(self, why: str) -> None:
        session, self._client = self._client, None
        if session is None:
            return
        if self.robot.running:
            self.robot.abort()
            self.log(f"task id {self.robot.task}: robot stopped (link lost)")
        with contextlib.suppress(OSError):
            session.sock.close()
        self.record("disconnect", conn=session.index, why=why)
        self.log(f"connection {session.index} closed: {why}")


@dataclass(frozen=True)
class _Corrupt:
    """A sample whose F_RX field reads ``nan`` or ``inf`` on the line."""

    sample: p.Sample
    kind: str

    def line(self) -> bytes:
        good = self.sample.line().decode().split(" ")
        good[4] = self.kind
        return " ".join(good).encode()


def _junk(fault: Fault) -> list[bytes]:
    """``n`` bad lines: text junk and non-ASCII bytes (garbage) or 300-byte lines (oversize)."""
    if fault.kind == "oversize":
        return [b"S 1.000 " + b"0" * 290 + b"\n"] * fault.n
    pool = [b"#~! garbage 1 2\n", b"S 1.0 \xff\xfe 2.0 3.0 4.0\n", b"S 1.0 2.0\n"]
    return [pool[i % len(pool)] for i in range(fault.n)]

"""The bridge core: NACHI-PEEL 1 task state machine and the link's safety rules, without ROS.

:class:`NachiBridge` runs one thread that owns the connection (docs/nachi.md):

* **connect**: :meth:`~.link.Connection.open` (TCP + ``HELLO`` + version check); on failure it
  logs why and retries after :class:`~.link.Backoff` delays; ``link.give_up_s`` bounds how long a
  waiting task tolerates that (:attr:`NachiBridge.gave_up`);
* **states**: ``disconnected`` -> ``idle`` -(:meth:`request_task`: ``START``)-> ``starting``
  -(``OK START``)-> ``running`` -(``STOP``)-> ``stopping`` -> ``idle``; ``DONE`` / ``ALARM`` end a
  running task at once, a lost link ends it as ``aborted`` and returns to ``disconnected``;
* **commands**: :meth:`command` (the planner's speed, mm/s) goes out as ``V`` only while the
  task it answers runs, and only inside ``[safety.u_min_mmps, safety.u_max_mmps]`` (default the
  controller's 0-20 mm/s: a speed outside is clamped, a non-finite one dropped, both counted
  and logged at most every few seconds); after ``STOP`` or a lost link nothing more is
  forwarded;
* **safety**, in the reading loop, one line at a time:

  - a sample with |F_RX| or |F_RZ| >= ``safety.f_prewarn_n`` (20 N, 4.2) sends ``STOP`` before
    the sample is published and before the next line is parsed; the delay from the arrival of
    the sample's bytes to ``STOP`` in the kernel is measured (:attr:`BridgeStats.stop_delays_s`);
  - malformed, oversize and non-finite lines are counted per kind and logged; a run of
    ``safety.bad_line_limit`` of them during a task sends ``STOP``;
  - no sample for ``safety.stall_timeout_s`` of wall time during a task sends ``STOP``;
  - with ``safety.slowdown.enabled``, every sample's force scales the planner's command (the
    slowdown zone of Eq. M6, :mod:`peel_bridge.slowdown`, as the simulator bridge runs it): a
    new ``V`` goes out when that changes the last ``V`` sent, and the command again once the
    force is below ``safety.slowdown.start_n``;
  - no ``DONE`` within ``safety.stop_timeout_s`` of ``STOP``: the link is closed and reopened;
  - the controller's ``ALARM`` (``10 watchdog`` when the planner went silent) ends the task and
    is recorded in the trajectory's meta.

Everything reaches the owner through a :class:`Listener` (samples, finished tasks, log lines),
called from the bridge thread with no lock held.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from peel_bridge.slowdown import slowdown_line
from peel_msgs_py.wire import DropLog, SpeedLimits

from . import protocol as p
from .config import LinkParams, SafetyParams
from .link import Backoff, Connection, LinkError, Received
from .task import OUTCOME_OF, TaskRecorder, TaskResult, alarm_outcome

DISCONNECTED, IDLE, STARTING, RUNNING, STOPPING = (
    "disconnected", "idle", "starting", "running", "stopping")
#: Longest wait of the reading loop, s (deadlines are checked at least this often).
POLL_S = 0.02


class Listener(Protocol):
    def on_sample(self, index: int, sample: p.Sample) -> None: ...
    def on_task_end(self, result: TaskResult) -> None: ...
    def on_log(self, level: str, text: str) -> None: ...


@dataclass
class BridgeStats:
    connects: int = 0
    connect_failures: int = 0
    disconnects: int = 0
    bad_lines: dict[str, int] = field(default_factory=lambda: dict.fromkeys(p.BAD_KINDS, 0))
    stops: dict[str, int] = field(default_factory=dict)
    alarms: list[str] = field(default_factory=list)
    refused_v: int = 0
    dropped_commands: int = 0
    clamped_commands: int = 0
    stop_delays_s: list[float] = field(default_factory=list)
    last_failure: str = ""


class NachiBridge:
    """The bridge core (module docstring). ``start()`` it, ``request_task(k)``, ``close()``."""

    def __init__(self, link: LinkParams, safety: SafetyParams, listener: Listener) -> None:
        self.link, self.safety, self.listener = link, safety, listener
        self.stats = BridgeStats()
        self.limits = SpeedLimits(safety.u_min_mmps, safety.u_max_mmps)
        self._zone = safety.slowdown.zone(safety.f_prewarn_n)  # Eq. M6, per task
        self._u_cmd: float | None = None  # the planner's command in force (before Eq. M6)
        self._u_sent: float | None = None  # the last V sent for it (after Eq. M6)
        self._drops = DropLog()
        self.gave_up: str | None = None
        self._lock = threading.Lock()  # state, task, connection (with the node's command())
        self._state = DISCONNECTED
        self._conn: Connection | None = None
        self._task: TaskRecorder | None = None
        self._pending: int | None = None
        self._stop_asked: str | None = None  # stop_task(): STOP the task once it runs
        self._starting: int | None = None
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self._backoff = Backoff(link.backoff_initial_s, link.backoff_max_s, link.backoff_factor)
        self._retry_at = 0.0
        self._down_since = time.monotonic()
        self._bad_run = 0
        self._deadline: float | None = None  # OK START / DONE after STOP / PONG
        self._last_sample = 0.0
        self._next_ping = 0.0
        self._ending: tuple[str, str, str] | None = None  # (outcome, reason, detail) after STOP

    # ------------------------------------------------------------------ public API
    @property
    def state(self) -> str:
        return self._state

    @property
    def controller_id(self) -> str | None:
        conn = self._conn
        return conn.hello.controller_id if conn else None

    def start(self, conn: Connection | None = None) -> NachiBridge:
        """Start the thread, serving ``conn`` (connected, HELLO checked) if given."""
        if conn is not None:
            self._adopt(conn)
        self._thread = threading.Thread(target=self._run, name="nachi-bridge", daemon=True)
        self._thread.start()
        return self

    def close(self, timeout_s: float = 10.0) -> None:
        """Stop the thread; a running task is stopped first (``STOP``, wait for ``DONE``)."""
        self._closing.set()
        if self._thread is not None:
            self._thread.join(timeout_s)

    def request_task(self, index: int) -> None:
        """Run task ``index`` as soon as the link is idle (``START``)."""
        with self._lock:
            self._pending = index

    def stop_task(self, reason: str) -> None:
        """Drop a requested task and ``STOP`` a starting or running one (it ends ``aborted``
        with ``reason``), from the link's thread."""
        with self._lock:
            self._pending, self._stop_asked = None, reason

    @property
    def busy(self) -> bool:
        """A task is requested, starting or running."""
        return self._pending is not None or self._state in (STARTING, RUNNING, STOPPING)

    def command(self, u_mmps: float, index: int) -> bool:
        """Forward the planner's speed (mm/s) for task ``index`` as ``V``; False if dropped."""
        if not math.isfinite(u_mmps):
            self.stats.dropped_commands += 1
            self._log_drop(self._drops.drop("/peel/cmd_vel", "twist.linear.x",
                                            f"is not finite ({u_mmps!r}); not forwarded"))
            return False
        held = self.limits.clamp(u_mmps)
        if held != u_mmps:
            self.stats.clamped_commands += 1
            self._log_drop(self._drops.drop(
                "/peel/cmd_vel", "twist.linear.x", f"= {u_mmps:g} mm/s is outside "
                f"{self.limits.describe()}; forwarding {held:g} mm/s", action="clamped"))
            u_mmps = held
        with self._lock:
            task, conn = self._task, self._conn
            if self._state != RUNNING or task is None or task.index != index or conn is None:
                self.stats.dropped_commands += 1
                return False
            self._u_cmd = u_mmps
            u_mmps = self._u_sent = self._zone.limit(u_mmps)  # Eq. M6 after the latest sample
            try:
                conn.send(p.Velocity(u_mmps))
            except LinkError:
                return False  # the reading thread sees the broken link and ends the task
            task.command_sent(u_mmps)
        return True

    def _log_drop(self, line: str | None) -> None:
        if line is not None:
            self._log("warn", line)

    # ------------------------------------------------------------------ the thread
    def _run(self) -> None:
        while not self._closing.is_set():
            try:
                if self._conn is None:
                    self._connect()
                else:
                    self._serve_once()
            except LinkError as exc:
                self._link_lost(str(exc))
            except Exception as exc:  # a bug must not leave the robot moving: drop the link
                self._link_lost(f"internal error {type(exc).__name__}: {exc}")
        self._shutdown()

    def _notify(self, fn: Callable[..., None], *args: object) -> None:
        """Call the listener; its failure is printed, never raised into the link's thread."""
        try:
            fn(*args)
        except Exception as exc:
            print(f"nachi bridge: listener {getattr(fn, '__name__', fn)} failed: "
                  f"{type(exc).__name__}: {exc}", file=sys.stderr, flush=True)

    def _log(self, level: str, text: str) -> None:
        self._notify(self.listener.on_log, level, text)

    def _connect(self) -> None:
        wait = self._retry_at - time.monotonic()
        if wait > 0:
            self._closing.wait(min(wait, 0.1))
            return
        lk = self.link
        try:
            conn = Connection.open(lk.host, lk.port, lk.connect_timeout_s, lk.hello_timeout_s)
        except LinkError as exc:
            self._connect_failed(str(exc))
            return
        self._adopt(conn)

    def _adopt(self, conn: Connection) -> None:
        """Serve ``conn`` (HELLO checked) from now on."""
        lk = self.link
        failures = self.stats.connect_failures
        with self._lock:
            self._conn, self._state = conn, IDLE
        self.stats.connects += 1
        self._backoff.reset()
        self._bad_run, self._deadline = 0, None
        self._next_ping = time.monotonic() + lk.ping_interval_s
        again = " (reconnected)" if self.stats.connects > 1 else ""
        self._log("info", f"connected to controller {conn.hello.controller_id} at {conn.peer} "
                          f"({p.PROTOCOL} {p.VERSION}){again}; {failures} failed attempts so far")

    def _connect_failed(self, why: str) -> None:
        self.stats.connect_failures += 1
        self.stats.last_failure = why
        delay = self._backoff.next()
        self._retry_at = time.monotonic() + delay
        self._log("warn", f"{why}; retrying in {delay:.2f} s")
        down = time.monotonic() - self._down_since
        if self.link.give_up_s > 0 and self._pending is not None and down >= self.link.give_up_s:
            self.gave_up = (f"no controller at {self.link.host}:{self.link.port} for {down:.1f} s "
                            f"({self.stats.connect_failures} attempts; last: {why})")

    def _serve_once(self) -> None:
        now = time.monotonic()
        if self._stop_asked is not None and self._state in (RUNNING, IDLE, DISCONNECTED):
            with self._lock:
                reason, self._stop_asked = self._stop_asked, None
            self._stop_task("aborted", reason, f"{reason}: the task is stopped")
        if self._state == IDLE:
            self._idle_duties(now)
        conn = self._conn
        assert conn is not None
        if conn.receive(self._wait(now)):
            while self._conn is conn and (item := conn.pop()) is not None:
                self._handle(item)
        self._check_deadlines(time.monotonic())

    def _wait(self, now: float) -> float:
        return POLL_S if self._deadline is None else min(POLL_S, max(0.0, self._deadline - now))

    def _idle_duties(self, now: float) -> None:
        conn = self._conn
        assert conn is not None
        with self._lock:
            index, self._pending = self._pending, None
            if index is not None:
                self._state, self._starting = STARTING, index
        if index is not None:
            conn.send(p.Start())
            self._deadline = now + self.link.reply_timeout_s
            self._log("info", f"task {index + 1}: START")
        elif self._deadline is None and now >= self._next_ping:
            conn.send(p.Ping())
            self._deadline = now + self.link.reply_timeout_s
            self._next_ping = now + self.link.ping_interval_s

    # ------------------------------------------------------------------ lines
    def _handle(self, item: Received) -> None:
        if item.raw == p.OVERSIZE:
            self._bad(p.OVERSIZE, f"line over {p.MAX_LINE} bytes")
            return
        try:
            msg = p.parse_controller(item.raw)  # type: ignore[arg-type]
        except p.LineError as exc:
            self._bad(exc.kind, f"{exc.detail}: {p.preview(item.raw)}")
            return
        if isinstance(msg, p.Sample):
            self._on_sample(msg, item.at)
            return
        self._bad_run = 0
        if isinstance(msg, p.OkStart):
            self._on_ok_start(msg)
        elif isinstance(msg, p.Done):
            self._on_done(msg)
        elif isinstance(msg, p.Alarm):
            self._on_alarm(msg)
        elif isinstance(msg, p.Err):
            self._on_err(msg)
        elif isinstance(msg, p.Pong):
            if self._state == IDLE:
                self._deadline = None
        elif not isinstance(msg, p.OkStop):
            self._log("warn", f"unexpected {type(msg).__name__} in state {self._state}")

    def _bad(self, kind: str, detail: str) -> None:
        self.stats.bad_lines[kind] += 1
        self._bad_run += 1
        task = self._task
        if task is not None:
            task.bad_lines[kind] += 1
        self._log("warn", f"bad line ({kind}, {self._bad_run} in a row): {detail}")
        if self._state == RUNNING and self._bad_run >= self.safety.bad_line_limit:
            self._stop_task("aborted", "bad_lines", f"{self._bad_run} bad lines in a row")

    def _on_sample(self, s: p.Sample, at: float) -> None:
        task = self._task
        if task is None or self._state not in (RUNNING, STOPPING):
            self._log("warn", f"sample t={s.t:.3f} outside a task ignored")
            return
        if task.samples and not s.t > task.samples[-1].t:
            self._bad(p.MALFORMED, f"sample t={s.t:.3f} does not follow t={task.samples[-1].t:.3f}")
            return
        self._bad_run = 0
        f = self.safety.f_prewarn_n
        if self._state == RUNNING and (abs(s.fx) >= f or abs(s.fz) >= f):
            self._stop_task("safety_stop", "prewarning",
                            f"prewarning |F| >= {f:g} N at t={s.t:.3f} s (fx={s.fx:.2f}, "
                            f"fz={s.fz:.2f} N)", at)
        task.add(s)
        self._slow_down(task, s)
        self._last_sample = time.monotonic()
        self._notify(self.listener.on_sample, task.index, s)

    def _slow_down(self, task: TaskRecorder, s: p.Sample) -> None:
        """Eq. M6 after sample ``s``: the planner's command scaled by its force, sent as ``V``
        when that changes the last ``V`` (and the command again once the force is low). A ``V``
        the controller refused is not sent again."""
        self._zone.measured(s.fx, s.fz)
        with self._lock:
            conn, u_cmd = self._conn, self._u_cmd
            if self._state != RUNNING or conn is None or u_cmd is None:
                return
            u = self._zone.speed(u_cmd)
            if u == self._u_sent:
                return
            self._u_sent = u
            try:
                conn.send(p.Velocity(u))
            except LinkError:
                return
            task.command_sent(u)

    def _on_ok_start(self, msg: p.OkStart) -> None:
        conn = self._conn
        if self._state != STARTING or self._starting is None or conn is None:
            self._log("warn", f"unexpected OK START {msg.task_id} in state {self._state}")
            return
        rec = TaskRecorder(self._starting, conn.hello.controller_id, msg.task_id)
        with self._lock:
            self._task, self._state, self._starting = rec, RUNNING, None
            self._u_cmd = self._u_sent = None
            self._zone.reset()
        self._deadline, self._bad_run, self._ending = None, 0, None
        self._last_sample = time.monotonic()
        self._log("info", f"task {rec.index + 1}: running (controller task id {msg.task_id})")

    def _on_done(self, msg: p.Done) -> None:
        task = self._task
        if task is None:
            return  # the DONE that follows an ALARM, or a stale one: nothing to end
        task.done_t_s = msg.t
        if self._ending is not None:
            self._finish(*self._ending)
            return
        # DONE alarm without an ALARM line before it: an alarm of unknown code
        outcome = OUTCOME_OF.get(msg.reason, "aborted")
        self._finish(outcome, msg.reason, f"DONE {msg.t:.3f} {msg.reason}")

    def _on_alarm(self, msg: p.Alarm) -> None:
        text = f"{msg.code} {msg.text}"
        self.stats.alarms.append(text)
        self._log("error", f"controller ALARM {text}")
        task = self._task
        if task is None:
            return
        task.alarm = text
        if self._ending is not None:
            outcome, reason, detail = self._ending
            self._finish(outcome, reason, f"{detail}; then ALARM {text}")
        else:
            self._finish(alarm_outcome(msg.code), "alarm", f"ALARM {text}")

    def _on_err(self, msg: p.Err) -> None:
        text = f"ERR {msg.code} {msg.text}"
        if self._state == STARTING:
            self._not_started("start_refused", f"controller refused START: {text}")
            return
        task = self._task
        if msg.code in (p.ERR_RANGE, p.ERR_NO_TASK) and task is not None:
            task.command_refused(msg)
            self.stats.refused_v += 1
            self._log("warn", f"task {task.index + 1}: controller refused V: {text}; "
                              f"{task.u_in_force:.3f} mm/s stays in force")
            return
        self._log("warn", f"controller answered {text}")

    # ------------------------------------------------------------------ ending tasks
    def _stop_task(self, outcome: str, reason: str, detail: str, at: float | None = None) -> None:
        """Send STOP now (the first thing done); the task ends with ``outcome`` at DONE."""
        with self._lock:
            conn, task = self._conn, self._task
            if self._state != RUNNING or conn is None or task is None:
                return
            self._state = STOPPING
            sent = conn.send(p.Stop())
        self._ending = (outcome, reason, detail)
        self._deadline = time.monotonic() + self.safety.stop_timeout_s
        self.stats.stops[reason] = self.stats.stops.get(reason, 0) + 1
        delay = ""
        if at is not None:
            task.stop_delay_s = sent - at
            self.stats.stop_delays_s.append(sent - at)
            delay = f" {1e3 * (sent - at):.3f} ms after the sample arrived"
        self._log("warn", f"task {task.index + 1}: {detail}: STOP sent{delay}")

    def _finish(self, outcome: str, reason: str, detail: str) -> None:
        with self._lock:
            task, self._task = self._task, None
            self._state = IDLE if self._conn is not None else DISCONNECTED
        self._deadline, self._ending = None, None
        self._next_ping = time.monotonic() + self.link.ping_interval_s
        if task is None:
            return
        result = task.result(outcome, reason, detail)
        zone = self._zone.as_dict()
        if result.trajectory is not None:
            result.trajectory.meta["slowdown"] = zone
        line = slowdown_line(task.index + 1, zone)
        if line is not None:
            self._log("info", line)
        level = "info" if outcome in ("done", "timeout") else "warn"
        self._log(level, f"task {task.index + 1}: {outcome} ({detail}), {len(task.samples)} samples")
        self._notify(self.listener.on_task_end, result)

    def _not_started(self, reason: str, detail: str) -> None:
        with self._lock:
            index, self._starting = self._starting, None
            self._state = IDLE if self._conn is not None else DISCONNECTED
        self._deadline = None
        if index is not None:
            self._log("error", f"task {index + 1}: not started: {detail}")
            self._notify(self.listener.on_task_end, TaskResult(index, False, "aborted", reason, detail))

    def _check_deadlines(self, now: float) -> None:
        state = self._state
        if state == RUNNING and now - self._last_sample > self.safety.stall_timeout_s:
            self._stop_task("aborted", "stalled",
                            f"no sample for {1e3 * (now - self._last_sample):.0f} ms")
        if self._deadline is None or now < self._deadline:
            return
        if state == STOPPING and self._ending is not None:
            outcome, reason, detail = self._ending
            self._finish(outcome, reason, f"{detail}; no DONE within "
                                          f"{self.safety.stop_timeout_s:g} s of STOP")
            raise LinkError("controller did not confirm STOP; closing the link")
        if state == STARTING:
            raise LinkError(f"no OK START within {self.link.reply_timeout_s:g} s")
        if state == IDLE:
            raise LinkError(f"no PONG within {self.link.reply_timeout_s:g} s")

    def _link_lost(self, why: str) -> None:
        with self._lock:
            conn, self._conn = self._conn, None
            was = self._state
        if conn is not None:
            conn.close()
        self.stats.disconnects += 1
        self.stats.last_failure = why
        self._down_since = time.monotonic()
        self._retry_at = self._down_since + self._backoff.next()
        self._log("error", f"controller link lost: {why}; forwarding stopped, reconnecting "
                           f"with backoff")
        if was == STARTING:
            self._not_started("connection_lost", why)
        elif was in (RUNNING, STOPPING):
            outcome, reason, detail = self._ending or ("aborted", "connection_lost", why)
            self._finish(outcome, reason, detail if self._ending is None else f"{detail}; {why}")
        else:
            with self._lock:
                self._state = DISCONNECTED

    def _shutdown(self) -> None:
        """The thread ends: stop a running task on the controller, then close the link."""
        if self._state == RUNNING:
            self._stop_task("aborted", "shutdown", "bridge shutting down")
        end = time.monotonic() + self.safety.stop_timeout_s
        try:
            while self._state == STOPPING and self._conn is not None and time.monotonic() < end:
                self._serve_once()
        except LinkError:
            pass
        if self._task is not None:
            self._finish(*(self._ending or ("aborted", "shutdown", "bridge shutting down")))
        if self._conn is not None:
            self._conn.close()
        with self._lock:
            self._conn, self._state = None, DISCONNECTED

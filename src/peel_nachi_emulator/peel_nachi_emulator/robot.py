"""The emulated controller's logic: one robot peeling on PeelEnv, driven by NACHI-PEEL 1 messages.

No sockets and no wall clock here: :class:`Robot` answers bridge messages (:meth:`Robot.command`)
and advances one 100 ms sample per :meth:`Robot.tick`, returning the controller's lines as
message objects; :mod:`.emulator` moves them over TCP at X times real time.

The physics is the simulator bridge's: :class:`peel_sim_node.env.PeelEnv` (``sim`` or ``plant``),
task ``k`` drawn from ``(seed, k)`` exactly as ``peel_sim_node`` and ``peel experiment`` draw it
(:func:`peel_sim_node.lockstep.task_params`, :func:`peel_msgs_py.task.task_seed`). The one change:
the env's own stop (``task.f_prewarn_n``) is moved to the controller's force alarm
(``force_alarm_n``, 25 N by default), because the 20 N prewarning (4.2) is the bridge's to act on.
The controller ends a task with ``DONE reached`` at q_ter, ``DONE timeout`` at t_max,
``ALARM 20`` + ``DONE alarm`` at the force alarm and ``ALARM 10 watchdog`` + ``DONE alarm`` when
no ``V`` came for :data:`~.protocol.WATCHDOG_S` of controller time (a ``V`` refused for its
range still counts: the planner is alive; the speed in force stays).
"""

from __future__ import annotations

from typing import Any

from peel_msgs_py.task import task_seed
from peel_nachi_bridge import protocol as p
from peel_sim_node.config import SimConfig, load_sim_config
from peel_sim_node.env import PeelEnv
from peel_sim_node.lockstep import task_params


class Robot:
    """The controller's task state and the plant it moves."""

    def __init__(self, *, source: str = "sim", seed: int = 0, force_alarm_n: float = 25.0,
                 cfg: SimConfig | None = None) -> None:
        base = cfg if cfg is not None else load_sim_config()
        self.cfg = load_sim_config({**base.flat, "task.f_prewarn_n": float(force_alarm_n)})
        self.source, self.seed = source, int(seed)
        self.force_alarm_n = float(force_alarm_n)
        self.dt = float(self.cfg.task.dt_s)
        self.env = PeelEnv(self.cfg, source=source, seed=task_seed(self.seed, 0))
        self.running = False
        self.tasks_started = 0
        self.task = -1  # index of the current (or last) task
        self.u = 0.0  # speed in force, mm/s
        self.last_v_t = 0.0  # controller time of the last V (watchdog)
        self.t = 0.0  # controller time of the last sample of the current task

    # ------------------------------------------------------------------ commands
    def command(self, msg: Any, now_t: float) -> list[Any]:
        """Answer one bridge message received at task time ``now_t``; returns the reply lines."""
        if isinstance(msg, p.Start):
            return self._start()
        if isinstance(msg, p.Velocity):
            return self._velocity(msg.u, now_t)
        if isinstance(msg, p.Stop):
            if not self.running:
                return [p.OkStop()]
            self.running = False
            return [p.OkStop(), p.Done(max(now_t, self.t), "stopped")]
        if isinstance(msg, p.Ping):
            return [p.Pong(now_t)]
        raise TypeError(f"not a bridge message: {msg!r}")

    def _start(self) -> list[Any]:
        if self.running:
            return [p.Err(p.ERR_TASK_RUNNING, "task running")]
        k = self.tasks_started
        self.env.reset(seed=task_seed(self.seed, k),
                       params=task_params(self.cfg, self.seed, k, self.source))
        self.tasks_started += 1
        self.task, self.running = k, True
        self.u, self.last_v_t, self.t = 0.0, 0.0, 0.0
        return [p.OkStart(k), self.sample()]

    def _velocity(self, u: float, now_t: float) -> list[Any]:
        if not self.running:
            return [p.Err(p.ERR_NO_TASK, "no task running")]
        self.last_v_t = now_t
        if not p.V_MIN_MMPS <= u <= p.V_MAX_MMPS:
            return [p.Err(p.ERR_RANGE, f"V out of range {p.V_MIN_MMPS:g}..{p.V_MAX_MMPS:g} mm/s: "
                                       f"{u:.4f}")]
        self.u = u
        return []

    # ------------------------------------------------------------------ time
    def sample(self) -> p.Sample:
        h = self.env.history
        return p.Sample(float(h.t[-1]), float(h.q[-1]), float(h.v[-1]), float(h.fx[-1]),
                        float(h.fz[-1]))

    def tick(self) -> list[Any]:
        """One sample period under the speed in force: the new sample and how the task ends."""
        if not self.running:
            return []
        self.env.step(self.u)
        s = self.sample()
        self.t = s.t
        out: list[Any] = [s]
        outcome = self.env.outcome
        if outcome == "safety_stop":
            f = max(abs(s.fx), abs(s.fz))
            out += [p.Alarm(p.ALARM_FORCE, f"force {f:.1f} N"), p.Done(s.t, "alarm")]
        elif outcome == "done":
            out.append(p.Done(s.t, "reached"))
        elif outcome == "timeout":
            out.append(p.Done(s.t, "timeout"))
        elif s.t - self.last_v_t >= p.WATCHDOG_S - 1e-9:
            out += [p.Alarm(p.ALARM_WATCHDOG, "watchdog"), p.Done(s.t, "alarm")]
        if len(out) > 1:
            self.running = False
        return out

    def abort(self) -> None:
        """The link is gone: the robot stops where it is and the task ends (nothing is sent)."""
        self.running = False

    def close(self) -> None:
        self.env.close()

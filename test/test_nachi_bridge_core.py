"""The ROS-free bridge core against the controller emulator over real TCP (no DDS).

Every fault of the issue, each with its recorded outcome: the TaskResult / trajectory the bridge
produces, the bridge's counters, and the emulator's own record of what it received (so that
"STOP within the same sample" is checked on the controller's side, not taken from the bridge).
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable

import numpy as np
import pytest

from peel_msgs_py.task import task_seed
from peel_nachi_bridge import protocol as p
from peel_nachi_bridge.bridge import NachiBridge
from peel_nachi_bridge.config import load_config
from peel_nachi_bridge.link import Backoff
from peel_nachi_bridge.task import TaskResult
from peel_nachi_emulator.emulator import ControllerEmulator, EmulatorOptions
from peel_nachi_emulator.faults import parse_fault
from peel_nachi_emulator.robot import Robot
from peel_sim_node.config import load_sim_config
from peel_sim_node.env import PeelEnv
from peel_sim_node.lockstep import task_params

pytestmark = pytest.mark.process  # starts processes or real-time I/O: scripts/flaky.sh

Speed = Callable[[int, float], "float | None"]


class Driver:
    """Listener of the bridge that also plays the planner: at every control instant (every 5th
    sample) it sends ``speed(task, t)`` (mm/s; None = silent)."""

    def __init__(self, speed: Speed) -> None:
        self.speed = speed
        self.bridge: NachiBridge | None = None
        self.results: list[TaskResult] = []
        self.samples: dict[int, list[p.Sample]] = {}
        self.logs: list[tuple[str, str]] = []
        self.ended = threading.Condition()

    def on_sample(self, index: int, s: p.Sample) -> None:
        self.samples.setdefault(index, []).append(s)
        if round(s.t * 10) % 5 == 0 and self.bridge is not None:
            u = self.speed(index, s.t)
            if u is not None:
                self.bridge.command(u, index)

    def on_task_end(self, result: TaskResult) -> None:
        with self.ended:
            self.results.append(result)
            self.ended.notify_all()

    def on_log(self, level: str, text: str) -> None:
        self.logs.append((level, text))

    def wait(self, n: int, timeout_s: float = 60.0) -> list[TaskResult]:
        deadline = time.monotonic() + timeout_s
        with self.ended:
            while len(self.results) < n and time.monotonic() < deadline:
                self.ended.wait(0.1)
        return list(self.results)


def run(faults: tuple[str, ...] = (), *, tasks: int = 1, speed: Speed = lambda k, t: 4.0,
        emu_speed: float = 2.0, q_ter_mm: float = 6.0, started: Callable[..., None] | None = None,
        safety: dict[str, float] | None = None,
        **overrides: object) -> tuple[Driver, NachiBridge, ControllerEmulator]:
    """Run ``tasks`` started tasks through the bridge against a fresh emulator (``safety``:
    fields of the bridge's :class:`SafetyParams` replaced beyond what its parameters allow)."""
    robot = Robot(source="sim", seed=3, cfg=load_sim_config({"task.q_ter_mm": q_ter_mm}))
    opts = EmulatorOptions(port=0, speed=emu_speed, seed=3,
                           faults=tuple(parse_fault(f) for f in faults))
    emu = ControllerEmulator(opts, robot=robot, log=lambda text: None).start()
    cfg = load_config({"link.port": emu.port, "link.hello_timeout_s": 1.0, **overrides})
    driver = Driver(speed)
    bridge = NachiBridge(cfg.link, dataclasses.replace(cfg.safety, **(safety or {})), driver)
    driver.bridge = bridge
    bridge.start()
    try:
        index = 0
        while sum(r.started for r in driver.results) < tasks:
            bridge.request_task(index)
            n = len(driver.results)
            got = driver.wait(n + 1, 60.0)
            assert len(got) > n, f"task {index} did not end; logs: {driver.logs[-5:]}"
            index += int(got[-1].started)
            if started is not None:
                started(bridge, emu, got[-1])
    finally:
        bridge.close()
        emu.close()
    return driver, bridge, emu


def outcomes(driver: Driver) -> list[tuple[str, str]]:
    return [(r.outcome, r.reason) for r in driver.results if r.started]


def test_full_task_matches_the_simulator_bridge_physics() -> None:
    """A whole task: DONE reached -> ``done``; the samples are PeelEnv's for task k of the seed,
    sample for sample, as the simulator bridge would produce them under the same commands."""
    driver, bridge, emu = run(tasks=2, speed=lambda k, t: 3.0 if t < 1.0 else 4.5, emu_speed=1.0)
    assert outcomes(driver) == [("done", "reached"), ("done", "reached")]
    traj = driver.results[1].trajectory
    assert traj is not None and traj.meta["controller_task_id"] == 1
    assert traj.q[-1] >= 6.0 and np.all(np.diff(traj.t) > 0)
    np.testing.assert_allclose(np.diff(traj.t), 0.1, atol=1e-6)  # controller time, any speed
    # u column: the command in force over (t_k, t_k+1], 0 at the end
    assert set(np.round(traj.u[:-1], 4)) <= {3.0, 4.5} and traj.u[-1] == 0.0
    cfg = load_sim_config({"task.q_ter_mm": 6.0, "task.f_prewarn_n": 25.0})
    with PeelEnv(cfg, source="sim", seed=task_seed(3, 0)) as env:
        env.reset(seed=task_seed(3, 1), params=task_params(cfg, 3, 1, "sim"))
        for u in traj.u[:-1]:
            env.step(float(u))
        h = env.history
    np.testing.assert_allclose(traj.q, h.q, atol=1e-3)  # the line carries 4 decimals
    np.testing.assert_allclose(traj.fx, h.fx, atol=1e-3)
    np.testing.assert_allclose(traj.fz, h.fz, atol=1e-3)
    assert bridge.stats.connects == 1 and bridge.stats.disconnects == 0
    assert not emu.of_kind("refused_v") and len(emu.of_kind("v")) >= 4


def test_dropped_connection_aborts_the_task_and_reconnects() -> None:
    driver, bridge, emu = run(("drop:t=0.5,task=0",), tasks=2)
    assert outcomes(driver) == [("aborted", "connection_lost"), ("done", "reached")]
    first = driver.results[0].trajectory
    assert first is not None and first.t[-1] == pytest.approx(0.4)  # nothing after the drop
    assert bridge.stats.connects == 2 and bridge.stats.disconnects == 1
    assert [e.data["conn"] for e in emu.of_kind("connect")] == [0, 1]
    assert any("link lost" in text and "reconnecting" in text for _, text in driver.logs)
    assert any("(reconnected)" in text for _, text in driver.logs)


def test_garbage_oversize_nan_inf_are_counted_and_never_published() -> None:
    faults = ("garbage:t=0.2,n=2", "oversize:t=0.4", "nan:t=0.6", "inf:t=0.8")
    driver, bridge, _ = run(faults)
    assert outcomes(driver) == [("done", "reached")]
    traj = driver.results[0].trajectory
    assert traj is not None
    assert traj.meta["bad_lines"] == {"oversize": 1, "malformed": 2, "non_finite": 2}
    assert bridge.stats.bad_lines == {"oversize": 1, "malformed": 2, "non_finite": 2}
    assert np.all(np.isfinite(traj.as_array()[:, :6]))
    sent = [round(s.t, 1) for s in driver.samples[0]]
    assert 0.6 not in sent and 0.8 not in sent and 0.4 in sent  # corrupt samples dropped
    warnings = [text for level, text in driver.logs if level == "warn" and "bad line" in text]
    assert len(warnings) == 5


def test_a_run_of_bad_lines_stops_the_task() -> None:
    driver, bridge, emu = run(("garbage:t=0.5,n=3",))
    assert outcomes(driver) == [("aborted", "bad_lines")]
    assert bridge.stats.stops == {"bad_lines": 1}
    assert len(emu.of_kind("stop")) == 1


def test_stalled_stream_stops_the_task() -> None:
    # speed 1: the controller's watchdog (1 s of controller time) comes after the bridge's
    # 300 ms stall rule; at X > 3.3 it would come first
    driver, _bridge, emu = run(("stall:t=0.6,s=3",), emu_speed=1.0)
    assert outcomes(driver) == [("aborted", "stalled")]
    stop = emu.of_kind("stop")
    assert len(stop) == 1 and 0.8 <= stop[0].data["t"] < 1.5  # 0.3 s wall after the last sample
    assert not emu.of_kind("alarm")


def test_force_spike_sends_stop_within_the_same_sample() -> None:
    driver, bridge, emu = run(("spike:t=0.5,f=22",), emu_speed=1.0)
    assert outcomes(driver) == [("safety_stop", "prewarning")]
    traj = driver.results[0].trajectory
    assert traj is not None and traj.fx[-1] == pytest.approx(22.0) and traj.t[-1] == pytest.approx(0.5)
    (stop,) = emu.of_kind("stop")
    assert stop.data["sample_t"] == pytest.approx(0.5)  # the controller had sent no later sample
    delay = driver.results[0].stop_delay_s
    assert delay is not None and delay > 0 and bridge.stats.stop_delays_s == [delay]
    # STOP went out before the spiked sample was handed on (and before any later line)
    (i_stop,) = [i for i, (_, text) in enumerate(driver.logs) if "STOP sent" in text]
    assert "prewarning" in driver.logs[i_stop][1]


def test_the_slowdown_zone_scales_v_at_the_sample_and_restores_the_command_after() -> None:
    """Eq. M6 on the Nachi bridge: a sample reporting 18.5 N between two control instants makes
    the bridge send V = (20 - 18.5) / 3 x 4 = 2 mm/s at once, and V 4 after the next sample
    (back under 17 N); the trajectory's u holds the speed in force, its meta what the zone did."""
    driver, _bridge, emu = run(("spike:t=0.7,f=18.5",), emu_speed=1.0,
                              **{"safety.slowdown.enabled": True})
    assert outcomes(driver) == [("done", "reached")]
    sent = [e.data["u"] for e in emu.of_kind("v")]
    i = sent.index(2.0)
    assert sent[i + 1] == 4.0 and sent.count(2.0) == 1
    traj = driver.results[0].trajectory
    assert traj is not None
    k = int(np.argmin(np.abs(traj.t - 0.7)))
    assert traj.fx[k] == pytest.approx(18.5) and traj.u[k] == pytest.approx(2.0)
    assert np.all(traj.u[:-1][np.arange(len(traj) - 1) != k] == 4.0)
    stats = traj.meta["slowdown"]
    assert stats["enabled"] and stats["samples_slowed"] == 1 and stats["min_scale"] == 0.5
    assert any("slowdown zone (Eq. M6" in text and "slowed 1 of" in text
               for _, text in driver.logs)


def test_controller_force_alarm_ends_the_task_as_safety_stop() -> None:
    # the bridge's prewarning set above the controller's 25 N: the controller's alarm acts
    driver, _bridge, _emu = run(speed=lambda k, t: 20.0, q_ter_mm=25.0,
                              **{"safety.f_prewarn_n": 100.0})
    assert outcomes(driver) == [("safety_stop", "alarm")]
    traj = driver.results[0].trajectory
    assert traj is not None and traj.meta["alarm"].startswith("20 force")
    assert max(abs(traj.fx[-1]), abs(traj.fz[-1])) >= 25.0


@pytest.mark.parametrize("fault", ["no-hello:conn=0", "bad-hello:conn=0,version=2"])
def test_bad_greeting_is_retried_with_backoff(fault: str) -> None:
    driver, bridge, _emu = run((fault,))
    assert outcomes(driver) == [("done", "reached")]
    assert bridge.stats.connect_failures == 1 and bridge.stats.connects == 1
    want = "no HELLO" if fault.startswith("no-") else "speaks NACHI-PEEL 2"
    assert any(want in text and "retrying in" in text for _, text in driver.logs)


def test_controller_that_never_says_hello_makes_the_bridge_give_up() -> None:
    emu = ControllerEmulator(EmulatorOptions(port=0, faults=(parse_fault("no-hello"),)),
                             log=lambda text: None).start()
    cfg = load_config({"link.port": emu.port, "link.hello_timeout_s": 0.3,
                       "link.give_up_s": 1.0, "link.backoff_max_s": 0.4})
    driver = Driver(lambda k, t: 4.0)
    bridge = NachiBridge(cfg.link, cfg.safety, driver).start()
    bridge.request_task(0)
    deadline = time.monotonic() + 30
    while bridge.gave_up is None and time.monotonic() < deadline:
        time.sleep(0.05)
    bridge.close()
    emu.close()
    assert bridge.gave_up is not None and "no HELLO" in bridge.gave_up
    assert bridge.stats.connect_failures >= 2 and bridge.stats.connects == 0
    assert driver.results == [] and bridge.busy  # the task never started


def test_a_speed_outside_the_limits_is_clamped_before_it_goes_out() -> None:
    """-3 and 1e9 mm/s from the planner (or anyone): the controller sees 0 and 20 mm/s."""
    def speed(k: int, t: float) -> float:
        return -3.0 if 0.4 < t < 0.6 else 1e9 if 0.9 < t < 1.1 else 4.0
    driver, bridge, emu = run(speed=speed)
    assert outcomes(driver) == [("done", "reached")]
    sent = [e.data["u"] for e in emu.of_kind("v")]
    assert 20.0 in sent and 0.0 in sent and max(sent) == 20.0 and min(sent) == 0.0
    assert not emu.of_kind("refused_v") and bridge.stats.refused_v == 0
    assert bridge.stats.clamped_commands >= 2
    clamped = [text for _, text in driver.logs if text.startswith("clamped a /peel/cmd_vel")]
    # one line for both: the second clamp of the field within LOG_EVERY_S is only counted
    assert len(clamped) == 1 and "= -3 mm/s is outside 0-20 mm/s; forwarding 0 mm/s" in clamped[0]
    traj = driver.results[0].trajectory
    assert traj is not None and max(traj.u) == 20.0


def test_refused_v_is_recorded_and_the_task_goes_on() -> None:
    """The controller's own refusal (ERR 21), reached only by a bridge with wider limits."""
    driver, bridge, emu = run(speed=lambda k, t: 25.0 if 0.4 < t < 0.6 else 4.0,
                              safety={"u_max_mmps": 30.0})
    assert outcomes(driver) == [("done", "reached")]
    traj = driver.results[0].trajectory
    assert traj is not None and len(traj.meta["refused_v"]) == 1
    assert traj.meta["refused_v"][0].startswith("21 V out of range")
    assert bridge.stats.refused_v == 1
    (refused,) = emu.of_kind("refused_v")
    assert refused.data["u"] == 25.0 and refused.data["code"] == p.ERR_RANGE
    assert 25.0 not in set(traj.u)  # the speed in force stayed the accepted one


def test_silent_planner_trips_the_controller_watchdog() -> None:
    driver, bridge, emu = run(speed=lambda k, t: 4.0 if t < 0.4 else None)
    assert outcomes(driver) == [("aborted", "alarm")]
    traj = driver.results[0].trajectory
    assert traj is not None and traj.meta["alarm"] == "10 watchdog"
    # the last V arrived just after t = 0 (controller time): the sample at t = 1.1 is the
    # first that is 1.0 s later
    assert traj.t[-1] == pytest.approx(1.1)
    assert bridge.stats.alarms == ["10 watchdog"]
    assert emu.of_kind("alarm")[0].data["code"] == p.ALARM_WATCHDOG


def test_commands_go_out_only_for_the_running_task() -> None:
    def check(bridge: NachiBridge, emu: ControllerEmulator, result: TaskResult) -> None:
        assert not bridge.command(4.0, result.index)  # the task ended: dropped
        assert not bridge.command(float("nan"), result.index + 1)
    _driver, bridge, emu = run(started=check)
    assert bridge.stats.dropped_commands >= 2
    assert all(e.data["task"] == 0 for e in emu.of_kind("v"))


def test_closing_the_bridge_stops_a_running_task() -> None:
    emu = ControllerEmulator(EmulatorOptions(port=0, speed=2.0),
                             robot=Robot(cfg=load_sim_config()), log=lambda text: None).start()
    cfg = load_config({"link.port": emu.port})
    driver = Driver(lambda k, t: 2.0)
    bridge = NachiBridge(cfg.link, cfg.safety, driver)
    driver.bridge = bridge
    bridge.start().request_task(0)
    emu.wait_for("v", 120.0, count=2)
    bridge.close()
    emu.close()
    assert outcomes(driver) == [("aborted", "shutdown")]
    assert len(emu.of_kind("stop")) == 1


def test_no_controller_at_all_backs_off() -> None:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nobody listens there
    cfg = load_config({"link.port": port, "link.backoff_initial_s": 0.05,
                       "link.backoff_max_s": 0.2})
    driver = Driver(lambda k, t: 4.0)
    bridge = NachiBridge(cfg.link, cfg.safety, driver).start()
    deadline = time.monotonic() + 20
    while bridge.stats.connect_failures < 4 and time.monotonic() < deadline:
        time.sleep(0.05)
    bridge.close()
    assert bridge.stats.connect_failures >= 4
    delays = [float(text.rsplit("retrying in ", 1)[1].split()[0]) for _, text in driver.logs
              if "retrying in" in text]
    assert delays[:4] == [0.05, 0.1, 0.2, 0.2]
    assert "cannot connect" in bridge.stats.last_failure


def test_backoff_grows_and_resets() -> None:
    b = Backoff(0.2, 1.0, 2.0)
    assert [b.next() for _ in range(5)] == [0.2, 0.4, 0.8, 1.0, 1.0]
    b.reset()
    assert b.next() == 0.2


def test_a_failing_listener_does_not_kill_the_link(capfd: pytest.CaptureFixture[str]) -> None:
    class Broken(Driver):
        def on_sample(self, index: int, s: p.Sample) -> None:
            super().on_sample(index, s)
            if round(s.t, 1) == 0.3:
                raise RuntimeError("publisher gone")

    emu = ControllerEmulator(EmulatorOptions(port=0, speed=4.0, seed=3),
                             robot=Robot(seed=3, cfg=load_sim_config({"task.q_ter_mm": 6.0})),
                             log=lambda text: None).start()
    cfg = load_config({"link.port": emu.port})
    driver = Broken(lambda k, t: 4.0)
    bridge = NachiBridge(cfg.link, cfg.safety, driver)
    driver.bridge = bridge
    bridge.start().request_task(0)
    results = driver.wait(1, 60.0)
    bridge.close()
    emu.close()
    assert [(r.outcome, r.reason) for r in results] == [("done", "reached")]
    assert "listener on_sample failed: RuntimeError: publisher gone" in capfd.readouterr().err

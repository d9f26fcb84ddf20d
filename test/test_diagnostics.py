"""``/diagnostics``: every node's health (docs/interfaces.md, "Diagnostics").

The levels and key values are ROS-free functions, tested here without DDS; then real node
processes on rclpy are read by an outside rclpy node in this test process: the simulator
bridge, the planner and the learner through a task and a learner update, the planner refusing
a model swapped in from outside (WARN), and the Nachi bridge when the controller's stream
stalls (WARN) against the emulator.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from graph_helpers import FAST, SIM_TASKS, node_env, override_yaml

from model_learner_node.health import LearnerHealth
from peel_msgs_py import topics
from peel_msgs_py.diagnostics import ERROR, OK, WARN, DurationWindow, RecentRises, Status, make_status
from peel_msgs_py.modelinfo import ModelRecord, UpdateReport
from peel_nachi_bridge.bridge import DISCONNECTED, IDLE, BridgeStats
from peel_nachi_bridge.health import bridge_status
from peel_planner_node.config import PlannerConfig
from peel_planner_node.health import peak_force, planner_status
from peel_sim_node.health import sim_status

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------- without DDS
def test_the_worst_check_sets_level_and_message() -> None:
    s = make_status("x: y", "hw", [(WARN, "a"), (ERROR, "b"), (ERROR, "c")], {"f": 0.1234567, "n": None})
    assert (s.level, s.message, s.values) == (ERROR, "b; c", (("f", "0.123457"), ("n", "-")))
    assert make_status("x", "hw", [], {}, ok_message="fine").message == "fine"


def test_duration_window_and_recent_rises() -> None:
    w = DurationWindow(budget_s=0.5, size=3)
    assert w.summary() == (None, None, 0)
    for s in (0.1, 0.7, 0.2, 0.3):
        w.add(s)
    assert w.summary() == (0.3, 0.7, 1) and (w.count, w.over, w.last) == (4, 1, 0.3)
    for s in (0.1, 0.1, 0.1):
        w.add(s)
    assert w.summary() == (0.1, 0.1, 0) and w.over == 1  # out of the window, still counted
    r = RecentRises(hold_s=30.0)
    assert r.update({"a": 0, "b": 2}, now=100.0) == {"b"}
    assert r.update({"a": 1, "b": 2}, now=120.0) == {"a", "b"}
    assert r.update({"a": 1, "b": 2}, now=140.0) == {"a"}
    assert r.update({"a": 1, "b": 2}, now=151.0) == set()


def test_bridge_levels() -> None:
    stats, recent = BridgeStats(), RecentRises(hold_s=30.0)
    down = bridge_status(stats, DISCONNECTED, None, "127.0.0.1:1", None, recent, 0.0)
    assert down.level == ERROR and "no link" in down.message
    stats.connects = 2
    ok = bridge_status(stats, IDLE, None, "127.0.0.1:1", "emu", recent, 1.0)
    assert ok.level == OK and ok.value("reconnects") == "1" and ok.value("link state") == "idle"
    stats.stops["stalled"] = 1
    stalled = bridge_status(stats, IDLE, None, "127.0.0.1:1", "emu", recent, 2.0)
    assert stalled.level == WARN and "stalled" in stalled.message
    assert (stalled.value("stall STOPs"), stalled.value("STOPs")) == ("1", "1")
    assert bridge_status(stats, IDLE, None, "h:1", "emu", recent, 33.0).level == OK
    gave_up = bridge_status(stats, DISCONNECTED, "no controller", "h:1", None, recent, 34.0)
    assert gave_up.level == ERROR and gave_up.message == "giving up: no controller"


def test_planner_levels_latency_and_margins() -> None:
    cfg = PlannerConfig.from_params({})
    model = ModelRecord(0, "ab" * 32, "/m.safetensors")
    w = DurationWindow(budget_s=0.5)
    s = planner_status(w, cfg, model, None, 0, None)
    assert s.level == OK and s.message == "planning with model v0"
    assert (s.value("plan latency median (ms)"), s.value("task margin (N)")) == ("-", "-")
    assert s.value("planning margin (N)") == "5"  # 20 N prewarning - 15 N barrier onset
    for sec in (0.01, 0.02, 0.6):
        w.add(sec)
    s = planner_status(w, cfg, model, "model swap refused: garbage", 1, 12.5)
    assert s.level == WARN and "late commands" in s.message and "garbage" in s.message
    assert (s.value("plan latency median (ms)"), s.value("plan latency max (ms)")) == ("20", "600")
    assert (s.value("late commands"), s.value("task margin (N)")) == ("1", "7.5")
    for _ in range(3):
        w.add(0.9)
    assert planner_status(w, cfg, model, None, 1, None).level == ERROR
    assert peak_force([[0, 0, 0, 0, 3.0, -12.5, 0], [0, 0, 0, 0, 11.0, 1.0, 0]]) == 12.5


def test_learner_levels_follow_the_last_report() -> None:
    h = LearnerHealth()
    assert h.status(0).level == OK and h.status(0).message == "no update yet"
    h.record(UpdateReport("/l", 1, "swapped", path="/m1"), 0.5)
    assert h.status(0).level == OK and h.status(0).value("update time last (s)") == "0.5"
    h.record(UpdateReport("/l", 2, "refused", "model swap refused: non-finite"), 0.7)
    assert h.status(1).level == WARN and "non-finite" in h.status(1).message
    h.record(UpdateReport("/l", 3, "failed", "OSError: disk full"), 0.1)
    s = h.status(0)
    assert s.level == ERROR and s.value("last result") == "failed"
    assert (s.value("update time median (s)"), s.value("swapped updates")) == ("0.5", "1")


def test_sim_levels() -> None:
    assert sim_status("sim", "running", 0, 3, 0, 0.1, 2.0, None).level == OK
    waiting = sim_status("sim", "running", 0, 3, 0, 2.5, 2.0, None)
    assert waiting.level == WARN and "re-sending" in waiting.message
    assert sim_status("sim", "between", 1, 3, 0, None, 2.0, "aborted").level == WARN


def test_diagnostics_topic_is_a_jazzy_type_and_not_recorded() -> None:
    from rosbags.typesys import Stores, get_typestore

    spec = topics.topic(topics.DIAGNOSTICS)
    assert spec.type in get_typestore(Stores.ROS2_JAZZY).types and spec.rate_hz == 1.0
    assert topics.DIAGNOSTICS not in topics.RECORDED_TOPICS
    assert f"`{topics.DIAGNOSTICS}`" in topics.markdown_table()


# ------------------------------------------------------------------------- real processes
class Listener:
    """An outside rclpy node (its own context, this test's domain) keeping every status heard."""

    def __init__(self, domain: str) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=int(domain))
        self.node = Node("diagnostics_test", context=self.ctx)
        self.heard: list[Status] = []
        self.lock = threading.Lock()
        self.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self.on_array,
                                      topics.qos_profile(topics.DIAGNOSTICS, subscriber=True))
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.spin, daemon=True)
        self.thread.start()

    def spin(self) -> None:
        while not self.stop.is_set():
            self.executor.spin_once(timeout_sec=0.05)

    def on_array(self, msg: object) -> None:
        for s in msg.status:  # type: ignore[attr-defined]
            status = Status(s.name, s.level[0], s.message, s.hardware_id,
                            tuple((kv.key, kv.value) for kv in s.values))
            with self.lock:
                self.heard.append(status)

    def wait_for(self, name: str, cond: Callable[[Status], bool], timeout: float,
                 alive: Callable[[], bool] = lambda: True) -> Status:
        """The first status of ``name`` meeting ``cond``, heard within ``timeout`` s."""
        end = time.monotonic() + timeout
        while time.monotonic() < end and alive():
            with self.lock:
                match = [s for s in self.heard if s.name == name and cond(s)]
            if match:
                return match[0]
            time.sleep(0.1)
        with self.lock:
            last = [s for s in self.heard if s.name == name][-1:]
        raise AssertionError(f"no {name} status as wanted; last heard: {last}")

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5.0)
        self.node.destroy_node()
        self.ctx.try_shutdown()


def _stop(procs: list[subprocess.Popen[bytes]]) -> None:
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
    for proc in procs:
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _node(tmp: Path, name: str, *args: str) -> subprocess.Popen[bytes]:
    log = (tmp / f"{name}.log").open("wb")
    cmd = [sys.executable, "-m", f"{name}.node", "--ros-args", "--params-file",
           str(ROOT / "config" / f"{name}.yaml"), "--params-file", str(tmp / "override.yaml"), *args]
    return subprocess.Popen(cmd, env=node_env(), stdout=log, stderr=subprocess.STDOUT)


def _override(init: Path, out: Path) -> str:
    """The three nodes started on their own (no launcher): one task, seed 3, sim time."""
    return override_yaml(SIM_TASKS, FAST, {
        "/**": {"use_sim_time": True},
        "peel_sim_node": {"node": {"tasks": 1, "seed": 3}},
        "peel_planner_node": {"model": {"path": init}},
        "model_learner_node": {"node": {"init_model": init, "out_dir": out}},
    })


def _swap(node: object, path: Path) -> tuple[bool, str]:
    """Set the planner's model.path from the outside (rcl_interfaces/srv/SetParameters)."""
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    client = node.create_client(SetParameters, "/peel_planner_node/set_parameters")  # type: ignore[attr-defined]
    assert client.wait_for_service(timeout_sec=60)
    req = SetParameters.Request(parameters=[Parameter(name="model.path", value=ParameterValue(
        type=ParameterType.PARAMETER_STRING, string_value=str(path)))])
    done = threading.Event()
    future = client.call_async(req)
    future.add_done_callback(lambda _f: done.set())
    assert done.wait(60), "no answer from the planner"
    res = future.result().results[0]
    return bool(res.successful), str(res.reason)


@pytest.mark.process
def test_every_node_reports_and_a_refused_model_turns_the_planner_to_warn(
        tmp_path: Path, ros_domain: str) -> None:
    from test_graph_run import initial_model

    init = initial_model(tmp_path)
    (tmp_path / "override.yaml").write_text(_override(init, tmp_path / "models"))
    listener = Listener(ros_domain)
    procs = [_node(tmp_path, n) for n in ("peel_planner_node", "model_learner_node", "peel_sim_node")]
    alive = lambda: all(p.poll() is None for p in procs)  # noqa: E731
    try:
        learner = listener.wait_for("model_learner_node: online learning",
                                    lambda s: s.value("last result") == "swapped", 300, alive)
        sim = listener.wait_for("peel_sim_node: simulator bridge",
                                lambda s: s.value("phase") == "finished", 60, alive)
        planner = listener.wait_for("peel_planner_node: planning",
                                    lambda s: s.value("model version") == "1", 60, alive)
        garbage = tmp_path / "garbage.safetensors"
        garbage.write_bytes(os.urandom(256))
        ok, reason = _swap(listener.node, garbage)
        assert not ok and "refused" in reason
        refused = listener.wait_for("peel_planner_node: planning",
                                    lambda s: s.value("swaps refused") == "1", 30, alive)
    finally:
        listener.close()
        _stop(procs)
    logs = "\n".join((tmp_path / f"{n}.log").read_text(errors="replace") for n in
                     ("peel_planner_node", "model_learner_node", "peel_sim_node"))
    assert "Traceback" not in logs, logs[-3000:]
    assert learner.level == OK and learner.value("last task") == "1"
    assert float(learner.value("update time last (s)")) > 0 and learner.value("updates") == "1"
    assert sim.level == OK and sim.value("tasks finished") == "1"
    assert int(planner.value("plans")) >= 1 and planner.value("control period (ms)") == "500"
    median, worst = (float(planner.value(f"plan latency {k} (ms)")) for k in ("median", "max"))
    assert 0 < median <= worst
    assert planner.level == OK or int(planner.value("late commands")) > 0
    assert refused.level == WARN and "model swap refused" in refused.message, refused
    assert refused.value("model version") == "1"  # the last good model plans on


@pytest.mark.process
def test_a_stalled_controller_stream_turns_the_bridge_to_warn(tmp_path: Path, ros_domain: str) -> None:
    from nachi_rig import Rig, bridge_cmd
    from test_nachi_node import emulator

    emu = emulator(("stall:t=0.6,s=3,task=0",), 1.0, 6.0)
    port = emu.port
    rig = Rig(ros_domain, tmp_path / "bag", speed=lambda task, t: 4.0)
    listener = Listener(ros_domain)
    log = (tmp_path / "bridge.log").open("wb")
    proc = subprocess.Popen(bridge_cmd(port, **{
        "node.tasks": 1, "node.exit_when_done": False, "node.wait_model_s": 0.0,
        "node.wait_planner_s": 60.0}), env=node_env(), stdout=log, stderr=subprocess.STDOUT)
    name = "peel_nachi_bridge: controller link"
    try:
        up = listener.wait_for(name, lambda s: s.value("link state") != DISCONNECTED, 120,
                               lambda: proc.poll() is None)
        stalled = listener.wait_for(name, lambda s: s.value("stall STOPs") == "1", 120,
                                    lambda: proc.poll() is None)
    finally:
        listener.close()
        _stop([proc])
        rig.close()
        emu.close()
    assert up.hardware_id == f"127.0.0.1:{port}"
    assert stalled.level == WARN and "stalled" in stalled.message, stalled
    assert stalled.value("STOPs") == "1" and int(stalled.value("connects")) >= 1
    assert "Traceback" not in (tmp_path / "bridge.log").read_text(errors="replace")

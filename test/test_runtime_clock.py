"""Timers on simulated time: a node with ``use_sim_time`` follows ``/clock`` messages.

A second node publishes rosgraph_msgs/Clock over DDS in 0.1 s steps; the sim-time node's
0.5 s timer must fire exactly when sim time crosses each multiple of 0.5 s, however slowly or
quickly the steps come in wall time, and restart when the clock jumps back (a new episode).
"""

from __future__ import annotations

import os
import time

import pytest

os.environ["PEEL_RUNTIME"] = "dds"

from peel_msgs_py.runtime import Node, Parameter, SingleThreadedExecutor, Time, rclpy
from peel_msgs_py.runtime.msg import Clock


@pytest.fixture
def ros(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", str(10 + (os.getpid() * 3 + 13) % 200))
    rclpy.init(args=["prog", "--ros-args", "-p", "sim_node:use_sim_time:=true"])
    yield
    rclpy.try_shutdown()


def _publish_and_wait(ex, pub, node, ns: int) -> None:
    msg = Clock(clock=Time(nanoseconds=ns).to_msg())
    pub.publish(msg)
    end = time.monotonic() + 10
    while node.get_clock().now().nanoseconds != ns:
        assert time.monotonic() < end, f"/clock {ns} never arrived"
        ex.spin_once(timeout_sec=0.05)
    while True:  # run whatever became due at this sim time
        before = len(ex._fired)
        ex.spin_once(timeout_sec=0.0)
        if len(ex._fired) == before:
            break


def test_timer_follows_clock_messages(ros) -> None:
    sim = Node("sim_node")  # use_sim_time from the node-scoped -p
    wall = Node("clock_pub")
    assert sim.get_parameter("use_sim_time").value is True
    assert wall.get_parameter("use_sim_time").value is False
    assert sim.get_clock().now().nanoseconds == 0  # sim time is zero before the first /clock
    ex = SingleThreadedExecutor()
    ex._fired = []
    sim.create_timer(0.5, lambda: ex._fired.append(sim.get_clock().now().nanoseconds))
    pub = wall.create_publisher(Clock, "/clock", 10)
    ex.add_node(sim)
    ex.add_node(wall)
    end = time.monotonic() + 10
    while pub.get_subscription_count() == 0:
        assert time.monotonic() < end
        ex.spin_once(timeout_sec=0.05)

    for step in range(1, 21):  # 0.1 .. 2.0 s
        _publish_and_wait(ex, pub, sim, step * 100_000_000)
        if step == 7:
            time.sleep(0.6)  # wall time passing must not fire a sim-time timer
    assert ex._fired == [500_000_000, 1_000_000_000, 1_500_000_000, 2_000_000_000]

    _publish_and_wait(ex, pub, sim, 3_200_000_000)  # a jump over two periods fires once
    assert ex._fired[-1] == 3_200_000_000 and len(ex._fired) == 5
    _publish_and_wait(ex, pub, sim, 3_400_000_000)  # next call was moved to 3.5 s
    assert len(ex._fired) == 5
    _publish_and_wait(ex, pub, sim, 3_500_000_000)
    assert ex._fired[-1] == 3_500_000_000

    _publish_and_wait(ex, pub, sim, 100_000_000)  # clock jumps back: a new episode
    for step in range(2, 7):
        _publish_and_wait(ex, pub, sim, step * 100_000_000)
    assert ex._fired[-1] == 600_000_000 and len(ex._fired) == 7

    # switching sim time off returns the node to the system clock
    assert sim.set_parameters([Parameter("use_sim_time", value=False)])[0].successful
    assert abs(sim.get_clock().now().nanoseconds - time.time_ns()) < 5_000_000_000
    sim.destroy_node()
    wall.destroy_node()

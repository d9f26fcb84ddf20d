"""Two OS processes exchange WrenchStamped and TwistStamped over the embedded DDS runtime.

A talker process publishes both types from a 50 Hz timer; a listener process subscribes with
the same QoS and reports what it received as JSON. Then the talker is stopped with SIGTERM and
with SIGINT and must exit cleanly (status 0, its ``finally`` block ran).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

TALKER = r"""
import sys
from peel_msgs_py.runtime import ExternalShutdownException, Node, rclpy
from peel_msgs_py.runtime.msg import TwistStamped, WrenchStamped

rclpy.init(args=sys.argv)
node = Node("talker")
wpub = node.create_publisher(WrenchStamped, "/peel/wrench", 100)
tpub = node.create_publisher(TwistStamped, "peel/twist", 100)  # relative name, same topic
k = [0]

def tick():
    w = WrenchStamped()
    w.header.stamp = node.get_clock().now().to_msg()
    w.header.frame_id = "blade"
    w.wrench.force.x = 0.5 * k[0]
    w.wrench.force.z = -1.0 - k[0]
    v = TwistStamped()
    v.header.frame_id = "blade"
    v.twist.linear.x = 0.001 * k[0]
    wpub.publish(w)
    tpub.publish(v)
    k[0] += 1
    if k[0] == 1:
        print("talker publishing", flush=True)

node.create_timer(0.02, tick)
try:
    rclpy.spin(node)
except (KeyboardInterrupt, ExternalShutdownException) as exc:
    print("talker stopped by", type(exc).__name__, flush=True)
finally:
    node.destroy_node()
    rclpy.try_shutdown()
print("talker clean exit", flush=True)
"""

LISTENER = r"""
import json, sys, time
from peel_msgs_py.runtime import Node, rclpy
from peel_msgs_py.runtime.msg import TwistStamped, WrenchStamped

N = int(sys.argv[1])
rclpy.init()
node = Node("listener")
wrenches, twists = [], []
node.create_subscription(
    WrenchStamped, "/peel/wrench",
    lambda m: wrenches.append([m.wrench.force.x, m.wrench.force.z, m.header.frame_id,
                               m.header.stamp.sec]), 100)
node.create_subscription(
    TwistStamped, "/peel/twist",
    lambda m: twists.append([m.twist.linear.x, m.header.frame_id]), 100)
end = time.monotonic() + 40
while (len(wrenches) < N or len(twists) < N) and time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.1)
print(json.dumps({"wrench": wrenches, "twist": twists}), flush=True)
node.destroy_node()
rclpy.shutdown()
"""


def _env(tag: int) -> dict[str, str]:
    env = dict(os.environ)
    env["PEEL_RUNTIME"] = "dds"
    env["ROS_DOMAIN_ID"] = str(10 + (os.getpid() * 3 + tag) % 200)
    env.pop("CYCLONEDDS_URI", None)
    env.pop("PEEL_DDS_NETWORK", None)
    return env


def _start(script: Path, *args: str, env: dict[str, str]) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, str(script), *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _wait_line(proc: subprocess.Popen, text: str, timeout: float = 30.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        line = proc.stdout.readline()
        if text in line:
            return
        if not line and proc.poll() is not None:
            break
    raise AssertionError(f"process never printed {text!r}; stderr: {proc.stderr.read()}")


def test_two_processes_exchange_wrench_and_twist(tmp_path: Path) -> None:
    (tmp_path / "talker.py").write_text(TALKER)
    (tmp_path / "listener.py").write_text(LISTENER)
    env = _env(1)
    listener = _start(tmp_path / "listener.py", "20", env=env)
    talker = _start(tmp_path / "talker.py", env=env)
    try:
        out, err = listener.communicate(timeout=60)
        assert listener.returncode == 0, err
        data = json.loads(out.strip().splitlines()[-1])
        wrenches, twists = data["wrench"], data["twist"]
        assert len(wrenches) >= 20 and len(twists) >= 20
        ks = [round(fx / 0.5) for fx, _, _, _ in wrenches]
        # reliable, keep-last 100: once matched, every sample arrives, in order
        assert ks == list(range(ks[0], ks[0] + len(ks)))
        for (fx, fz, frame, sec), k in zip(wrenches, ks, strict=True):
            assert fx == 0.5 * k and fz == -1.0 - k and frame == "blade"
            assert sec > 1_600_000_000  # stamped with the (system) ROS clock
        tk = [round(vx / 0.001) for vx, _ in twists]
        assert tk == list(range(tk[0], tk[0] + len(tk)))
        assert all(frame == "blade" for _, frame in twists)
    finally:
        talker.send_signal(signal.SIGTERM)
        out, err = talker.communicate(timeout=30)
        listener.kill() if listener.poll() is None else None
    assert talker.returncode == 0, err
    assert "talker stopped by ExternalShutdownException" in out
    assert "talker clean exit" in out
    assert "Traceback" not in err


@pytest.mark.parametrize(
    ("sig", "by"), [(signal.SIGINT, "KeyboardInterrupt"), (signal.SIGTERM, "ExternalShutdown")]
)
def test_signal_stops_spin_cleanly(tmp_path: Path, sig: int, by: str) -> None:
    (tmp_path / "talker.py").write_text(TALKER)
    talker = _start(tmp_path / "talker.py", env=_env(2))
    try:
        _wait_line(talker, "talker publishing")
    finally:
        talker.send_signal(sig)
        out, err = talker.communicate(timeout=30)
    assert talker.returncode == 0, err
    assert f"talker stopped by {by}" in out
    assert "talker clean exit" in out

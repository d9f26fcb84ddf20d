"""``peel record`` end to end: real rclpy publisher and recorder processes (raw subscriptions:
the CDR bytes as received, the offered QoS and type hash from the publishers' endpoint info)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from peel_bag import bagread
from peel_bag.bag import mcap_is_complete
from peel_msgs_py.errors import PeelError

pytestmark = pytest.mark.process  # starts processes or real-time I/O: scripts/flaky.sh

STORE = get_typestore(Stores.ROS2_JAZZY)
N = 50  # wrench messages published, force.x = index

PUBLISHER = textwrap.dedent(f"""
    import time
    import numpy as np
    import rclpy
    from geometry_msgs.msg import Vector3, Wrench, WrenchStamped
    from rclpy.duration import Duration
    from rclpy.node import Node
    from std_msgs.msg import Float64MultiArray, Int64
    from peel_msgs_py import codec, topics as T
    from peel_msgs_py.ros.messages import trajectory_msg
    from peel_msgs_py.trajectory import Trajectory
    rclpy.init()
    node = Node("fake_sim")
    kinds = {{T.WRENCH: WrenchStamped, T.MODEL_VERSION: Int64, T.TRAJECTORY: Float64MultiArray}}
    pubs = {{n: node.create_publisher(kinds[n], n, T.qos_profile(n)) for n in kinds}}
    pubs[T.MODEL_VERSION].publish(Int64(data=5))
    end = time.monotonic() + 60  # discovery: until the recorder's subscriptions matched
    while min(p.get_subscription_count() for p in pubs.values()) < 1 and time.monotonic() < end:
        time.sleep(0.05)
    for k in range({N}):
        m = WrenchStamped(wrench=Wrench(force=Vector3(x=float(k), z=-1.0)))
        m.header.frame_id = codec.task_frame_id(1)
        m.header.stamp.sec = k
        pubs[T.WRENCH].publish(m)
        time.sleep(0.04)
    traj = Trajectory(t=[0.0, 0.1], q=[0.0, 25.0], v=[0.0, 250.0], u=[5.0, 0.0], fx=[1.0, 2.0],
                      fz=[0.0, -1.0], psi=[np.nan, 0.1], outcome="timeout", params={{"mu": 0.5}},
                      meta={{"task_index": 1}})
    pubs[T.TRAJECTORY].publish(trajectory_msg(traj))
    acked = all(p.wait_for_all_acked(Duration(seconds=60)) for p in pubs.values())
    print("published" if acked else "not acknowledged", flush=True)
    node.destroy_node()
    rclpy.shutdown()
""")


def _start_recorder(bag, *extra: str) -> subprocess.Popen[str]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "peel_bringup.cli", "record", "--out", str(bag),
         "--flush-interval", "0.2", *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    line = proc.stderr.readline()
    assert "recording" in line, line + proc.stderr.read()
    return proc


def _publish() -> None:
    out = subprocess.run([sys.executable, "-c", PUBLISHER], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0 and "published" in out.stdout, out.stderr


def _wait_until_on_disk(bag, tmp) -> None:
    """Until the bag's flushed chunks hold the trajectory and the last wrench: the recorder's
    time-based flush has put everything on disk."""
    _wait_for(bag, tmp, lambda copy: len(bagread.read_trajectories(copy, repair=True)) == 1
              and bagread.read_topics(copy, repair=True)["/peel/wrench"]["fx_n"][-1] == N - 1)


def _wait_for(bag, tmp, ready) -> None:
    """Until ``ready(copy)`` holds for a repaired copy of the bag's flushed chunks."""
    deadline = time.monotonic() + 120  # only a hang reaches this
    while time.monotonic() < deadline:
        copy = tmp / f"copy_{time.monotonic_ns()}"
        shutil.copytree(bag, copy)
        try:
            if ready(copy):
                return
        except (PeelError, KeyError, ValueError, IndexError):
            pass  # nothing flushed yet
        finally:
            shutil.rmtree(copy)
        time.sleep(0.1)
    raise AssertionError("the recorder never flushed what the test waits for")


def _wrench_x(bag) -> list[float]:
    with Reader(bag) as reader:
        return [STORE.deserialize_cdr(raw, c.msgtype).wrench.force.x
                for c, _, raw in reader.messages() if c.topic == "/peel/wrench"]


def test_record_until_sigint(tmp_path, ros_domain) -> None:
    bag = tmp_path / "rec"
    rec = _start_recorder(bag)
    try:
        _publish()
    finally:
        rec.send_signal(signal.SIGINT)
        out, err = rec.communicate(timeout=60)
    assert rec.returncode == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["bag"] == str(bag) and summary["messages"] >= 20
    assert mcap_is_complete(bag / "rec_0.mcap")
    xs = _wrench_x(bag)
    assert len(xs) >= N // 2 and xs == [float(k) for k in range(int(xs[0]), N)]  # no gap
    arrays = bagread.read_topics(bag)
    assert arrays["/peel/model_version"]["version"].tolist() == [5]  # latched value recorded
    assert set(arrays["/peel/wrench"]["task"].tolist()) == {1}
    (traj,) = bagread.read_trajectories(bag)
    assert traj.outcome == "timeout" and traj.q[-1] == 25.0 and np.isnan(traj.psi[0])
    with Reader(bag) as reader:
        conns = {c.topic: c for c in reader.connections}
    # only topics that had publishers: as ros2 bag record, a channel per discovered topic
    assert set(conns) == {"/peel/wrench", "/peel/model_version", "/peel/trajectory"}
    assert conns["/peel/wrench"].msgtype == "geometry_msgs/msg/WrenchStamped"
    assert conns["/peel/wrench"].digest == STORE.hash_rihs01("geometry_msgs/msg/WrenchStamped")
    latched = conns["/peel/model_version"].ext.offered_qos_profiles[0]
    assert latched.durability.name.lower() == "transient_local"
    # mcap's own ROS 2 decoder reads the same messages
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(bag / "rec_0.mcap", "rb") as fh:
        decoded = [(c.topic, m) for _, c, _, m in make_reader(
            fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages()]
    assert [m.wrench.force.x for t, m in decoded if t == "/peel/wrench"] == xs
    assert [m.data for t, m in decoded if t == "/peel/model_version"] == [5]


def test_sigkilled_recorder_keeps_flushed_chunks(tmp_path, ros_domain) -> None:
    bag = tmp_path / "rec"
    rec = _start_recorder(bag, "--topics", "/peel/wrench", "/peel/model_version",
                          "/peel/trajectory")
    try:
        _publish()
        _wait_until_on_disk(bag, tmp_path)
    finally:
        os.kill(rec.pid, signal.SIGKILL)
        rec.communicate(timeout=60)
    assert rec.returncode == -signal.SIGKILL
    assert not mcap_is_complete(bag / "rec_0.mcap")
    arrays = bagread.read_topics(bag, repair=True)
    xs = arrays["/peel/wrench"]["fx_n"].tolist()
    assert len(xs) >= N // 2 and xs == [float(k) for k in range(int(xs[0]), N)]
    assert len(bagread.read_trajectories(bag)) == 1



LATE = textwrap.dedent("""
    import sys
    import rclpy
    from rclpy.duration import Duration
    from rclpy.node import Node
    from std_msgs.msg import Float64MultiArray, Int64
    from peel_msgs_py import topics as T
    from peel_msgs_py.ros.messages import trajectory_msg
    from peel_msgs_py.trajectory import Trajectory

    def task(k):
        return trajectory_msg(Trajectory(t=[0.0, 0.1], q=[0.0, 25.0], v=[0.0, 250.0], u=[5.0, 0.0],
                                         fx=[1.0, 2.0], fz=[0.0, -1.0], psi=[0.1, 0.1], outcome="done",
                                         params={}, meta={"task_index": k}))

    rclpy.init()
    node = Node("fake_sim")
    traj = node.create_publisher(Float64MultiArray, T.TRAJECTORY, T.qos_profile(T.TRAJECTORY))
    version = node.create_publisher(Int64, T.MODEL_VERSION, T.qos_profile(T.MODEL_VERSION))
    version.publish(Int64(data=3))
    traj.publish(task(1))  # peeled before anyone records
    print("ready", flush=True)
    while min(p.get_subscription_count() for p in (traj, version)) < 1:
        rclpy.spin_once(node, timeout_sec=0.05)
    traj.publish(task(2))
    ok = traj.wait_for_all_acked(Duration(seconds=60)) and version.wait_for_all_acked(Duration(seconds=60))
    print("published" if ok else "not acknowledged", flush=True)
    sys.stdin.readline()  # alive until the test has stopped the recorder
    node.destroy_node()
    rclpy.shutdown()
""")


def test_a_late_recorder_takes_the_current_model_but_no_task_peeled_before_it(tmp_path,
                                                                                ros_domain) -> None:
    """``/peel/trajectory`` keeps a bridge's last 10 tasks (transient local) for a learner that
    comes back; a recorder started later records the latched model version, and only the task
    that finished while it ran."""
    pub = subprocess.Popen([sys.executable, "-c", LATE], stdin=subprocess.PIPE,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert pub.stdout.readline().strip() == "ready", pub.stderr.read()
        bag = tmp_path / "late"
        rec = _start_recorder(bag)
        try:
            assert pub.stdout.readline().strip() == "published"
            _wait_for(bag, tmp_path, lambda copy: len(bagread.read_trajectories(copy, repair=True)) >= 1)
        finally:
            rec.send_signal(signal.SIGINT)
            _, err = rec.communicate(timeout=60)
        assert rec.returncode == 0, err
    finally:
        pub.communicate("\n", timeout=60)
    assert [t.meta["task_index"] for t in bagread.read_trajectories(bag)] == [2]
    assert bagread.read_topics(bag)["/peel/model_version"]["version"].tolist() == [3]

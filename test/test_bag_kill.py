"""A recording SIGKILLed mid-run (a real subprocess) still yields every complete chunk."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap

import pytest
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from peel_bag import bagread
from peel_bag.bag import mcap_is_complete
from peel_bag.bagrepair import repair_bag
from peel_msgs_py.errors import PeelError

pytestmark = pytest.mark.process  # starts processes or real-time I/O: scripts/flaky.sh

STORE = get_typestore(Stores.ROS2_JAZZY)

# Writes wrench messages whose force.x is their index. Mode "explicit": 5 chunks of 10 flushed
# by hand, then 7 messages left in the open chunk. Mode "size": 300 messages cut into chunks by
# size only. Prints how many messages are in flushed chunks, then waits to be killed.
WRITER = textwrap.dedent("""
    import sys, time
    from peel_bag.bag import BagWriter
    from geometry_msgs.msg import Vector3, Wrench, WrenchStamped
    from rclpy.serialization import serialize_message
    from peel_msgs_py.topics import STREAM_QOS
    path, mode = sys.argv[1], sys.argv[2]
    bag = BagWriter(path, chunk_size=1500 if mode == "size" else 10**9, flush_interval_s=3600)
    bag.open()
    bag.add_topic("/peel/wrench", "geometry_msgs/msg/WrenchStamped", [STREAM_QOS])
    def put(i):
        m = WrenchStamped(wrench=Wrench(force=Vector3(x=float(i), z=-1.0)))
        m.header.stamp.sec = i
        bag.write("/peel/wrench", serialize_message(m), 1_000_000 + i)
    if mode == "explicit":
        for i in range(57):
            put(i)
            if i % 10 == 9 and i < 50:
                bag.flush()
    else:
        for i in range(300):
            put(i)
    print("ready", bag.flushed_count, bag.message_count, flush=True)
    time.sleep(600)
""")


def _record_and_kill(path, mode: str) -> tuple[int, int]:
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path), mode],
                            stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline().split()
        assert line[0] == "ready", line
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    return int(line[1]), int(line[2])


def _forces(bag) -> list[float]:
    with Reader(bag) as reader:
        assert [c.msgtype for c in reader.connections] == ["geometry_msgs/msg/WrenchStamped"]
        return [STORE.deserialize_cdr(raw, c.msgtype).wrench.force.x
                for c, _, raw in reader.messages()]


@pytest.mark.parametrize("mode", ["explicit", "size"])
def test_killed_recording_keeps_complete_chunks(tmp_path, mode: str) -> None:
    bag = tmp_path / "killed"
    flushed, written = _record_and_kill(bag, mode)
    assert 0 < flushed < written
    if mode == "explicit":
        assert (flushed, written) == (50, 57)
    mcap = bag / "killed_0.mcap"
    size_before = mcap.stat().st_size
    assert not mcap_is_complete(mcap)
    with pytest.raises(PeelError, match="peel record --repair"):
        bagread.read_topics(bag)

    # the real CLI repairs it; rosbags then reads exactly the messages of the complete chunks
    out = subprocess.run([sys.executable, "-m", "peel_bringup.cli", "record", "--repair",
                          str(bag)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    assert report["repaired"] is True and report["messages"] == flushed
    assert mcap_is_complete(mcap)
    assert _forces(bag) == [float(i) for i in range(flushed)]
    orig = bag / "killed_0.mcap.orig"
    assert orig.stat().st_size == size_before  # the original is kept as it was
    # a complete bag is left alone
    assert repair_bag(bag).repaired is False


def test_repair_on_read_and_metadata(tmp_path) -> None:
    bag = tmp_path / "k2"
    flushed, _ = _record_and_kill(bag, "explicit")
    arrays = bagread.read_topics(bag, repair=True)
    assert arrays["/peel/wrench"]["fx_n"].tolist() == [float(i) for i in range(flushed)]
    with Reader(bag) as reader:
        assert reader.message_count == flushed
        assert reader.duration == flushed  # log times 1_000_000 + i, ns; duration + 1


def test_repair_refuses_a_bag_with_nothing_complete(tmp_path) -> None:
    bag = tmp_path / "empty"
    bag.mkdir()
    (bag / "empty_0.mcap").write_bytes(b"\x89MCAP0\r\n\x01")
    with pytest.raises(PeelError, match="no complete chunk"):
        repair_bag(bag)


def test_cut_at_any_byte_keeps_the_chunks_before_the_cut(tmp_path) -> None:
    """Truncating a bag anywhere (a write torn by the kill) keeps exactly the chunks before it."""
    import ros_msgs as M
    from mcap.reader import make_reader

    from peel_bag.bag import BagWriter

    src = tmp_path / "full"
    with BagWriter(src, chunk_size=800) as bag:
        bag.add_topic("/peel/pose", "geometry_msgs/msg/PoseStamped")
        for i in range(120):
            m = M.PoseStamped(pose=M.Pose(position=M.Point(x=float(i))))
            bag.write("/peel/pose", M.serialize(m), 5000 + i)
    data = (src / "full_0.mcap").read_bytes()
    with open(src / "full_0.mcap", "rb") as fh:
        chunks = sorted(make_reader(fh).get_summary().chunk_indexes,
                        key=lambda c: c.chunk_start_offset)
    assert len(chunks) >= 4
    ends = [c.chunk_start_offset + c.chunk_length for c in chunks]
    per_chunk = []
    with open(src / "full_0.mcap", "rb") as fh:
        reader = make_reader(fh)
        times = [m.log_time for _, _, m in reader.iter_messages()]
    for c in chunks:
        per_chunk.append(sum(c.message_start_time <= t <= c.message_end_time for t in times))
    for k, c in enumerate(chunks[:-1]):
        for cut in (c.chunk_start_offset + c.chunk_length // 2,  # inside chunk k
                    c.chunk_start_offset + c.chunk_length + 3):  # after it, in its index
            bag = tmp_path / f"cut{k}_{cut}"
            bag.mkdir()
            (bag / f"{bag.name}_0.mcap").write_bytes(data[:cut])
            keep = sum(per_chunk[: k + (cut > ends[k])])
            if keep == 0:  # cut inside the first chunk: nothing to keep
                with pytest.raises(PeelError, match="no complete chunk"):
                    repair_bag(bag)
                continue
            assert repair_bag(bag).messages == keep, (k, cut)
            with Reader(bag) as reader:
                xs = [STORE.deserialize_cdr(raw, cn.msgtype).pose.position.x
                      for cn, _, raw in reader.messages()]
            assert xs == [float(i) for i in range(keep)]

"""BagWriter: a bag read back by rosbags' own reader (messages, types, schemas, QoS) and mcap."""

from __future__ import annotations

import numpy as np
import pytest
import ros_msgs as M
import yaml
from mcap.reader import make_reader
from rosbags.interfaces import MessageDefinitionFormat
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from peel_bag import bagread
from peel_bag.bag import BagWriter, prepare_bag_dir
from peel_msgs_py import codec
from peel_msgs_py import topics as T
from peel_msgs_py.errors import PeelError
from peel_msgs_py.ros.messages import trajectory_msg
from peel_msgs_py.trajectory import Trajectory

STORE = get_typestore(Stores.ROS2_JAZZY)


def _stamped(t: float, task: int = 2) -> M.Header:
    sec, nanosec = codec.split_stamp(t)
    return M.Header(stamp=M.Time(sec=sec, nanosec=nanosec), frame_id=codec.task_frame_id(task))


def _messages(n: int) -> list[tuple[str, object]]:
    """A deterministic mix of every recorded topic, built with the runtime message classes."""
    out: list[tuple[str, object]] = []
    for k in range(n):
        t = 0.1 * k
        out.append((T.CLOCK, M.Clock(clock=M.Time(sec=int(t), nanosec=round(t % 1 * 1e9)))))
        out.append((T.WRENCH, M.WrenchStamped(
            header=_stamped(t), wrench=M.Wrench(force=M.Vector3(x=1.0 + k, z=-0.5 * k)))))
        out.append((T.TWIST, M.TwistStamped(
            header=_stamped(t), twist=M.Twist(linear=M.Vector3(x=0.001 * k)))))
        out.append((T.POSE, M.PoseStamped(
            header=_stamped(t), pose=M.Pose(position=M.Point(x=0.0001 * k)))))
        if k % 5 == 0:
            out.append((T.CMD_VEL, M.TwistStamped(
                header=_stamped(t), twist=M.Twist(linear=M.Vector3(x=0.004)))))
    out.append((T.MODEL_VERSION, M.Int64(data=3)))
    traj = Trajectory(t=np.arange(4) * 0.1, q=[0, 1, 2, 25.0], v=[0, 10, 10, 230.0],
                      u=[10, 10, 10, 0.0], fx=[1, 2, 3, 4.0], fz=[0, -1, -2, -3.0],
                      psi=[np.nan, 0.1, 0.2, 0.3], outcome="done", params={"mu": 0.3},
                      meta={"task": 0})
    out.append((T.TRAJECTORY, trajectory_msg(traj)))
    return out


def _record(path, msgs, raws: list[bytes] | None = None, **kw) -> BagWriter:
    """Write ``msgs`` serialized by rclpy; their bytes are appended to ``raws`` (rclpy leaves
    alignment padding uninitialised, so a second serialization may differ in those bytes)."""
    raws = [] if raws is None else raws
    with BagWriter(path, **kw) as bag:
        for name in T.RECORDED_TOPICS:
            bag.add_topic(name, T.topic(name).type, [T.topic(name).qos])
        for i, (name, msg) in enumerate(msgs):
            raws.append(M.serialize(msg))
            bag.write(name, raws[-1], 1_700_000_000_000_000_000 + i * 1000)
    return bag


def test_bag_reads_back_in_rosbags(tmp_path) -> None:
    msgs = _messages(60)
    raws: list[bytes] = []
    bag = _record(tmp_path / "run1", msgs, raws, chunk_size=4096)
    assert bag.chunks_written > 3  # several chunks, flushed by size
    assert sorted(p.name for p in (tmp_path / "run1").iterdir()) == ["metadata.yaml",
                                                                      "run1_0.mcap"]
    with Reader(tmp_path / "run1") as reader:
        conns = {c.topic: c for c in reader.connections}
        assert set(conns) == set(T.RECORDED_TOPICS)
        for name, conn in conns.items():
            assert conn.msgtype == T.topic(name).type
            assert conn.msgdef.format == MessageDefinitionFormat.MSG
            assert conn.msgdef.data == STORE.generate_msgdef(conn.msgtype, ros_version=2)[0]
            assert conn.digest == STORE.hash_rihs01(conn.msgtype)
            qos = conn.ext.offered_qos_profiles[0]
            assert qos.depth == T.topic(name).qos.depth
            assert qos.durability.name.lower() == T.topic(name).qos.durability
        got = [(c.topic, raw) for c, _, raw in reader.messages()]
        assert reader.message_count == len(msgs)
    # the same bytes, in order, and rosbags deserialises them to the messages rclpy reads
    assert got == [(name, raw) for (name, _), raw in zip(msgs, raws, strict=True)]
    for (name, raw), (_, m) in zip(got, msgs, strict=True):
        back = STORE.deserialize_cdr(raw, T.topic(name).type)
        assert bytes(STORE.serialize_cdr(back, T.topic(name).type)) == bytes(
            STORE.serialize_cdr(STORE.deserialize_cdr(M.serialize(m), T.topic(name).type),
                                T.topic(name).type))


def test_metadata_yaml_is_rosbag2_v9(tmp_path) -> None:
    msgs = _messages(10)
    _record(tmp_path / "b", msgs)
    info = yaml.safe_load((tmp_path / "b" / "metadata.yaml").read_text())
    info = info["rosbag2_bagfile_information"]
    assert info["version"] == 9 and info["storage_identifier"] == "mcap"
    assert info["relative_file_paths"] == ["b_0.mcap"]
    assert info["message_count"] == len(msgs)
    counts = {t["topic_metadata"]["name"]: t["message_count"]
              for t in info["topics_with_message_count"]}
    assert counts[T.WRENCH] == 10 and counts[T.CMD_VEL] == 2 and counts[T.TRAJECTORY] == 1
    assert not (tmp_path / "b" / ".metadata.yaml.tmp").exists()


def test_independent_mcap_reader_sees_ros2_profile_and_schemas(tmp_path) -> None:
    _record(tmp_path / "b", _messages(5))
    with open(tmp_path / "b" / "b_0.mcap", "rb") as fh:
        reader = make_reader(fh)
        header = reader.get_header()
        summary = reader.get_summary()
        n = sum(1 for _ in reader.iter_messages())
    assert header.profile == "ros2"
    assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
    assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
    assert all("offered_qos_profiles" in c.metadata for c in summary.channels.values())
    assert n == summary.statistics.message_count == len(_messages(5))


def test_bagread_arrays_in_paper_units_and_trajectories(tmp_path) -> None:
    _record(tmp_path / "b", _messages(20))
    arrays = bagread.read_topics(tmp_path / "b")
    np.testing.assert_allclose(arrays[T.POSE]["q_mm"], 0.1 * np.arange(20), rtol=1e-12)
    np.testing.assert_allclose(arrays[T.TWIST]["v_mmps"], np.arange(20.0), rtol=1e-12)
    np.testing.assert_allclose(arrays[T.CMD_VEL]["u_mmps"], 4.0)
    np.testing.assert_allclose(arrays[T.WRENCH]["fx_n"], 1.0 + np.arange(20))
    np.testing.assert_allclose(arrays[T.WRENCH]["t_s"], 0.1 * np.arange(20), atol=1e-9)
    assert arrays[T.MODEL_VERSION]["version"].tolist() == [3]
    assert set(arrays[T.POSE]["task"].tolist()) == {2}
    trajs = bagread.read_trajectories(tmp_path / "b")
    assert len(trajs) == 1 and trajs[0].q[-1] == 25.0 and trajs[0].outcome == "done"
    assert np.isnan(trajs[0].psi[0]) and trajs[0].params == {"mu": 0.3}


def test_time_based_flush_and_metadata_refresh(tmp_path) -> None:
    now = [0.0]
    bag = BagWriter(tmp_path / "b", chunk_size=10**9, flush_interval_s=1.0,
                    metadata_interval_s=0.0, monotonic=lambda: now[0]).open()
    meta = tmp_path / "b" / "metadata.yaml"
    assert yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]["message_count"] == 0
    bag.add_topic(T.MODEL_VERSION, "std_msgs/msg/Int64", [T.LATCHED_QOS])
    for k in range(3):
        bag.write(T.MODEL_VERSION, M.serialize(M.Int64(data=k)), 10 + k)
    bag.tick()
    assert bag.flushed_count == 0  # the chunk is younger than flush_interval_s
    now[0] = 1.5
    bag.tick()
    assert bag.flushed_count == 3 and bag.chunks_written == 1
    info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
    assert info["message_count"] == 3  # metadata.yaml counts what is on disk
    bag.close()


def test_bad_bag_paths_name_the_path(tmp_path) -> None:
    (tmp_path / "exists").mkdir()
    with pytest.raises(PeelError, match=r"exists.*already exists"):
        prepare_bag_dir(tmp_path / "exists")
    (tmp_path / "afile").write_text("x")
    with pytest.raises(PeelError, match="afile/sub"):
        prepare_bag_dir(tmp_path / "afile" / "sub")
    bag = BagWriter(tmp_path / "ok").open()
    with pytest.raises(PeelError, match="unknown message type 'foo_msgs/msg/Bar'"):
        bag.add_topic("/x", "foo_msgs/msg/Bar")
    with pytest.raises(PeelError, match="'/peel/wrench' was not added"):
        bag.write(T.WRENCH, b"\x00\x01\x00\x00", 1)
    bag.close()

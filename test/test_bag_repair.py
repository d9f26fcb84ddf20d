"""``peel record --repair`` on complete bags: intact ones are counted, a corrupt chunk is dropped.

The bags are written by our BagWriter, damaged byte by byte, repaired, and read back with two
independent readers: ``rosbags`` (its rosbag2 reader) and ``mcap``'s own reader with CRC checks.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from geometry_msgs.msg import Point, Pose, PoseStamped
from mcap.reader import make_reader
from rclpy.serialization import serialize_message
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from peel_bag.bag import BagWriter
from peel_bag.bagrepair import repair_bag

STORE = get_typestore(Stores.ROS2_JAZZY)
N = 120


@pytest.fixture(scope="module")
def full_bag(tmp_path_factory) -> dict:
    """A complete bag of N poses (x = index) in several chunks, and each chunk's messages."""
    src = tmp_path_factory.mktemp("repair") / "full"
    with BagWriter(src, chunk_size=800) as bag:
        bag.add_topic("/peel/pose", "geometry_msgs/msg/PoseStamped")
        for i in range(N):
            m = PoseStamped(pose=Pose(position=Point(x=float(i))))
            bag.write("/peel/pose", serialize_message(m), 5000 + i)
    with open(src / "full_0.mcap", "rb") as fh:
        chunks = sorted(make_reader(fh).get_summary().chunk_indexes,
                        key=lambda c: c.chunk_start_offset)
    xs = [float(i) for i in range(N)]
    members = [[x for x in xs if c.message_start_time <= 5000 + x <= c.message_end_time]
               for c in chunks]
    assert len(chunks) >= 4 and sum(len(m) for m in members) == N
    return {"bag": src, "chunks": chunks, "members": members}


def _copy(full: Path, dst: Path) -> Path:
    dst.mkdir()
    shutil.copy2(full / "full_0.mcap", dst / f"{dst.name}_0.mcap")
    return dst


def _flip(path: Path, offset: int) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0xFF
    path.write_bytes(bytes(data))


def _rosbags_xs(bag: Path) -> list[float]:
    with Reader(bag) as reader:
        return [STORE.deserialize_cdr(raw, c.msgtype).pose.position.x
                for c, _, raw in reader.messages()]


def _mcap_count(mcap: Path) -> int:
    with open(mcap, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        return sum(1 for _ in reader.iter_messages())


def _repair_cli(bag: Path) -> tuple[dict, str]:
    out = subprocess.run([sys.executable, "-m", "peel_bringup.cli", "record", "--repair",
                          str(bag)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout), out.stderr


def test_intact_bag_is_counted_and_left_alone(full_bag, tmp_path) -> None:
    bag = _copy(full_bag["bag"], tmp_path / "intact")
    before = (bag / "intact_0.mcap").read_bytes()
    report, _ = _repair_cli(bag)
    assert report["repaired"] is False
    assert report["messages"] == N and report["topics"] == {"/peel/pose": N}
    assert report["chunks"] == len(full_bag["chunks"]) and report["chunks_dropped"] == []
    assert (bag / "intact_0.mcap").read_bytes() == before
    assert not (bag / "intact_0.mcap.orig").exists()


@pytest.mark.parametrize("which", ["first", "middle", "last"])
def test_flipped_byte_in_a_chunk_drops_only_that_chunk(full_bag, tmp_path, which: str) -> None:
    chunks, members = full_bag["chunks"], full_bag["members"]
    k = {"first": 0, "middle": len(chunks) // 2, "last": len(chunks) - 1}[which]
    bag = _copy(full_bag["bag"], tmp_path / f"flip_{which}")
    mcap = bag / f"{bag.name}_0.mcap"
    c = chunks[k]
    _flip(mcap, c.chunk_start_offset + c.chunk_length - 20)  # inside the compressed records
    damaged = mcap.read_bytes()
    with pytest.raises(Exception):  # noqa: B017 - mcap's own CRC check refuses the file
        _mcap_count(mcap)

    report, err = _repair_cli(bag)
    keep = [x for j, m in enumerate(members) if j != k for x in m]
    assert report["repaired"] is True
    assert report["messages"] == len(keep) == N - len(members[k])
    assert report["topics"] == {"/peel/pose": len(keep)}
    assert report["chunks"] == len(chunks) - 1
    [dropped] = report["chunks_dropped"]
    assert dropped["offset"] == c.chunk_start_offset and dropped["bytes"] == c.chunk_length
    assert dropped["messages"] == len(members[k]) == report["messages_dropped"]
    assert "warning: dropped the chunk" in err
    # two independent readers agree: every message of every good chunk, in order
    assert _rosbags_xs(bag) == keep
    assert _mcap_count(mcap) == len(keep)
    with Reader(bag) as reader:
        assert reader.message_count == len(keep)
    assert (bag / f"{bag.name}_0.mcap.orig").read_bytes() == damaged


def test_broken_chunk_length_resumes_at_the_next_listed_chunk(full_bag, tmp_path) -> None:
    """A flipped byte in a chunk's length prefix: the summary's chunk index resynchronises."""
    chunks, members = full_bag["chunks"], full_bag["members"]
    bag = _copy(full_bag["bag"], tmp_path / "length")
    mcap = bag / "length_0.mcap"
    _flip(mcap, chunks[1].chunk_start_offset + 8)  # top byte of the record length
    result = repair_bag(bag)
    keep = [x for j, m in enumerate(members) if j != 1 for x in m]
    assert result.repaired and result.messages == len(keep)
    assert [d.offset for d in result.chunks_dropped] == [chunks[1].chunk_start_offset]
    assert result.messages_dropped is None  # its message index was skipped with it
    assert _rosbags_xs(bag) == keep

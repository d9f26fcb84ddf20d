"""The launcher's monitor node (``peel_bringup.monitor_node``): which model versions it counts as
announced. The planner announces each version on two latched topics at once
(``/peel/model_version``, and the record with its identity on ``/peel/model_info``); either one
arriving counts, so a latched sample DDS does not deliver to one reader loses no version."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from std_msgs.msg import Int64, String

from peel_bringup.monitor_node import GraphMonitor, close_monitor, open_monitor
from peel_msgs_py.modelinfo import ModelRecord

pytestmark = pytest.mark.process  # creates an rclpy node on a domain of its own


@pytest.fixture
def monitor(ros_domain: str) -> Iterator[GraphMonitor]:
    mon = open_monitor("model_learner_node")
    yield mon
    close_monitor(mon)


def _info(version: int) -> String:
    return String(data=ModelRecord(version, "ab" * 32, f"model_v{version}.safetensors").to_json())


def test_a_version_seen_only_on_model_info_is_announced(monitor: GraphMonitor) -> None:
    monitor.on_model_info(_info(0))
    monitor.on_model_info(_info(1))
    assert sorted(set(monitor.versions)) == [0, 1] and monitor.version == 1
    assert [r.version for r in monitor.updates.records] == [0, 1]


def test_a_late_redelivery_of_an_old_version_does_not_make_it_current(
        monitor: GraphMonitor) -> None:
    monitor.on_version(Int64(data=2))
    monitor.on_model_info(_info(1))  # latched, delivered again after the newer number
    monitor.on_version(Int64(data=1))
    assert monitor.version == 2 and sorted(set(monitor.versions)) == [1, 2]


def test_bad_announcements_are_dropped_and_counted(monitor: GraphMonitor) -> None:
    monitor.on_version(Int64(data=-1))
    monitor.on_model_info(String(data="{not json"))
    assert monitor.versions == [] and monitor.version is None
    assert monitor.drops.total == 2

"""The launcher's monitor node (``peel_bringup.monitor_node``): which model versions it counts as
the planner's. Any record of a version counts: the two latched topics the planner announces it
on at once (``/peel/model_version``, and the record with its identity on ``/peel/model_info``), a
finished trajectory's ``model_versions``, the learner's report of a swapped update; so a latched
sample DDS delivers late, or not at all, to one reader loses no version."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from std_msgs.msg import Int64, String

from peel_bringup.monitor_node import GraphMonitor, close_monitor, open_monitor
from peel_msgs_py.modelinfo import ModelRecord, UpdateReport
from peel_msgs_py.ros.messages import trajectory_msg
from peel_msgs_py.trajectory import Trajectory

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


def _trajectory(versions: list[int]) -> object:
    n = 4
    z = np.zeros(n)
    return trajectory_msg(Trajectory(t=np.arange(n) * 0.1, q=np.linspace(0.0, 1.0, n), v=z, u=z,
                                     fx=z, fz=z, psi=z, outcome="done",
                                     meta={"task_index": 0, "model_version": versions[0],
                                           "model_versions": versions}))


def test_versions_in_a_trajectory_and_a_swapped_report_are_announced(
        monitor: GraphMonitor) -> None:
    monitor.on_trajectory(_trajectory([0, 1]))
    assert len(monitor.trajectories) == 1 and sorted(set(monitor.versions)) == [0, 1]
    report = UpdateReport("model_learner_node", 1, "swapped", version=2)
    monitor.on_model_update(String(data=report.to_json()))
    assert monitor.version == 2 and sorted(set(monitor.versions)) == [0, 1, 2]


def test_a_refused_or_foreign_report_announces_nothing(monitor: GraphMonitor) -> None:
    for rep in (UpdateReport("model_learner_node", 1, "refused", reason="worse"),
                UpdateReport("someone_else", 1, "swapped", version=5)):
        monitor.on_model_update(String(data=rep.to_json()))
    assert monitor.versions == [] and monitor.version is None


def test_the_run_ends_only_once_a_swap_is_in_the_planners_record_too() -> None:
    """The learner's ``swapped`` report carries no version: the launcher also waits for the
    planner's record of that update (it may arrive after the report), else the summary's
    model versions would miss the last one."""
    from peel_bringup.graph import last_update_in
    from peel_msgs_py.modelinfo import REFUSED, SWAPPED, UpdateWait

    updates = UpdateWait("model_learner_node")
    assert not last_update_in(updates, 1)
    updates.add_report(UpdateReport("model_learner_node", 1, SWAPPED, path="/m1.safetensors"))
    assert not last_update_in(updates, 1)
    updates.add_record(ModelRecord(1, "ab" * 32, "/m1.safetensors", "someone_else", 1))
    assert not last_update_in(updates, 1)  # not the learner's update
    updates.add_record(ModelRecord(1, "ab" * 32, "/m1.safetensors", "model_learner_node", 1))
    assert last_update_in(updates, 1)
    updates.add_report(UpdateReport("model_learner_node", 2, REFUSED, "worse on held-out"))
    assert last_update_in(updates, 2)  # nothing for the planner to record


def test_a_monitor_matched_after_several_swaps_still_gets_every_record(ros_domain: str) -> None:
    """Discovery may match the launcher's reader with a planner's writer late (seconds on a
    loaded machine): the records of the swaps made before it must still reach it, in order, or
    the launcher waits for an update the planner made long ago. Here the reader only exists once
    five records are written; a writer that kept only its current record hands it v4 alone."""
    import time

    import rclpy

    from peel_msgs_py import topics

    rclpy.init()
    planner = rclpy.create_node("peel_planner_node")
    pub = planner.create_publisher(String, topics.MODEL_INFO, topics.qos_profile(topics.MODEL_INFO))
    records = [ModelRecord(v, f"{v:02x}" * 32, f"/m{v}.safetensors", "model_learner_node", v or None)
               for v in range(5)]
    for rec in records:
        pub.publish(String(data=rec.to_json()))
    mon = GraphMonitor("model_learner_node")
    try:
        deadline = time.monotonic() + 30.0
        while len(mon.updates.records) < len(records) and time.monotonic() < deadline:
            rclpy.spin_once(mon, timeout_sec=0.1)
            rclpy.spin_once(planner, timeout_sec=0.0)
        assert mon.updates.records == records
        assert all(mon.updates.outcome(k) is not None for k in range(1, 5))
    finally:
        mon.destroy_node()
        planner.destroy_node()
        rclpy.try_shutdown()

"""The plant bridges' task loop without ROS (peel_bridge.loop.TaskLoop): the graph's readers
before task 0; between tasks the learner's update of the task before, known by its identity
(peel_msgs_py.modelinfo.UpdateWait), as Algorithm 2 line 20 waits; a model swapped in by anyone
else does not end the wait (docs/graph.md)."""

from __future__ import annotations

import pytest

from peel_bridge.loop import RETRY_S, LoopParams, Readiness, TaskLoop, task_stamp_ns, to_ns
from peel_msgs_py.modelinfo import FAILED, SKIPPED, ModelRecord, UpdateReport, UpdateWait

LEARNER = "/model_learner_node"


def _loop(**node: object) -> tuple[TaskLoop, list[tuple[str, str]]]:
    values = {"tasks": 3, "wait_planner_s": 10.0, "wait_model_s": 30.0, "min_subscribers": 1,
              "min_traj_subscribers": 1, "exit_when_done": False, **node}
    logs: list[tuple[str, str]] = []
    params = LoopParams.from_params({f"node.{k}": v for k, v in values.items()})
    return TaskLoop(params, lambda level, text: logs.append((level, text))), logs


def _seen(updates: UpdateWait, version: int | None, readers: int = 5) -> Readiness:
    return Readiness(version, readers, readers, update=updates.outcome)


def _record(version: int, producer: str | None, task: int | None) -> ModelRecord:
    return ModelRecord(version=version, sha256=f"{version:064x}", path=f"m{version}.safetensors",
                       producer=producer, task=task)


def test_first_task_waits_for_the_model_and_the_readers_then_starts_anyway() -> None:
    loop, logs = _loop()
    updates = UpdateWait(LEARNER)
    assert loop.poll(0.0, _seen(updates, None)) is None  # no model yet
    assert loop.poll(1.0, _seen(updates, 0, readers=0)) is None  # no readers yet
    assert loop.phase == "wait_graph" and not logs
    assert loop.poll(2.0, _seen(updates, 0)) == 0
    assert loop.phase == "running"
    late, logs = _loop()
    assert late.poll(0.0, _seen(updates, None, readers=0)) is None
    assert late.poll(10.0, _seen(updates, None, readers=0)) == 0  # node.wait_planner_s ran out
    [(level, text)] = logs
    assert level == "warn" and text.startswith("starting without /peel/model_info")
    assert "subscribers of each state topic" in text and "/peel/trajectory" in text


def test_waits_for_the_learners_update_by_identity_not_by_number() -> None:
    loop, _ = _loop()
    updates = UpdateWait(LEARNER)
    updates.add_record(_record(0, None, None))
    assert loop.poll(0.0, _seen(updates, 0)) == 0
    assert loop.poll(0.5, _seen(updates, 0)) is None  # running
    loop.task_ended(1.0, 0)
    assert loop.poll(2.0, _seen(updates, 0)) is None
    updates.add_record(_record(1, None, None))  # swapped in from outside: not the update
    assert loop.poll(3.0, _seen(updates, 1)) is None
    updates.add_record(_record(2, LEARNER, 1))  # the learner's update after task 1
    assert loop.poll(4.0, _seen(updates, 2)) == 1


def test_a_failed_update_ends_the_wait_at_once_and_a_silent_one_after_the_timeout() -> None:
    loop, logs = _loop()
    updates = UpdateWait(LEARNER)
    assert loop.poll(0.0, _seen(updates, 0)) == 0
    loop.task_ended(1.0, 0)
    updates.add_report(UpdateReport(LEARNER, 1, FAILED, "probe batch: non-finite forces"))
    assert loop.poll(1.1, _seen(updates, 0)) == 1
    assert logs[-1] == ("warn", "the learner's update after task 1 failed: probe batch: "
                                "non-finite forces; going on with model v0")
    loop.task_ended(2.0, 1)
    assert loop.poll(20.0, _seen(updates, 0)) is None
    assert loop.poll(32.5, _seen(updates, 0)) == 2  # node.wait_model_s = 30 ran out
    assert logs[-1] == ("warn", "the learner's update after task 2 did not arrive within 30 s; "
                                "going on with model v0")


def test_no_wait_after_a_task_without_a_trajectory_or_with_the_wait_off() -> None:
    loop, _ = _loop()
    updates = UpdateWait(LEARNER)
    assert loop.poll(0.0, _seen(updates, 0)) == 0
    loop.task_ended(1.0, 0, published=False)
    assert loop.poll(1.1, _seen(updates, 0)) == 1  # the learner got nothing: nothing to wait for
    off, _ = _loop(wait_model_s=0.0)
    assert off.poll(0.0, _seen(updates, 0)) == 0
    off.task_ended(1.0, 0)
    assert off.poll(1.1, _seen(updates, 0)) == 1


def test_a_task_that_could_not_start_is_asked_for_again_and_not_counted() -> None:
    loop, _ = _loop()
    updates = UpdateWait(LEARNER)
    assert loop.poll(0.0, _seen(updates, 0)) == 0
    loop.task_ended(1.0, 0, started=False)
    assert loop.ended_tasks == 0
    assert loop.poll(1.0 + RETRY_S / 2, _seen(updates, 0)) is None
    assert loop.poll(1.0 + RETRY_S, _seen(updates, 0)) == 0  # the same task again


@pytest.mark.parametrize("exit_when_done", [False, True])
def test_finishes_after_the_last_tasks_update(exit_when_done: bool) -> None:
    loop, logs = _loop(tasks=2, exit_when_done=exit_when_done)
    updates = UpdateWait(LEARNER)
    assert loop.poll(0.0, _seen(updates, 0)) == 0
    loop.task_ended(1.0, 0)
    updates.add_report(UpdateReport(LEARNER, 1, SKIPPED, "too short"))
    assert loop.poll(1.1, _seen(updates, 0)) == 1
    loop.task_ended(2.0, 1)
    assert loop.poll(3.0, _seen(updates, 0)) is None
    assert not loop.finished and not loop.exit_now  # the last update is awaited too
    updates.add_record(_record(1, LEARNER, 2))
    assert loop.poll(4.0, _seen(updates, 1)) is None
    assert loop.finished and loop.ended_tasks == 2 and logs[-1] == ("info", "all 2 tasks done")
    assert loop.exit_now is exit_when_done
    assert loop.poll(5.0, _seen(updates, 1)) is None  # nothing more starts


def test_unbounded_tasks_never_finish() -> None:
    loop, _ = _loop(tasks=0, wait_model_s=0.0)
    updates = UpdateWait(LEARNER)
    for k in range(20):
        assert loop.poll(float(k), _seen(updates, 0)) == k
        loop.task_ended(k + 0.5, k)
    assert not loop.finished


def test_task_stamps_are_slot_plus_plant_time_in_integer_ns() -> None:
    slot = to_ns(100.0)
    assert task_stamp_ns(0, slot, 0.0) == 0
    assert task_stamp_ns(3, slot, 0.1) == 300_100_000_000
    assert task_stamp_ns(2, to_ns(20.0), 59.9) == 99_900_000_000
    assert [task_stamp_ns(1, slot, k * 0.1) - task_stamp_ns(1, slot, (k - 1) * 0.1)
            for k in range(1, 50)] == [100_000_000] * 49

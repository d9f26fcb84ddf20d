"""The Nachi bridge's task sequence without ROS: between tasks it waits for the learner's update
of the task before by its identity (peel_msgs_py.modelinfo.UpdateWait), as the simulator bridge
does; a model swapped in by anyone else does not end the wait (docs/graph.md)."""

from __future__ import annotations

from dataclasses import replace

from peel_msgs_py.modelinfo import FAILED, ModelRecord, UpdateReport, UpdateWait
from peel_nachi_bridge.config import load_config
from peel_nachi_bridge.sequencer import Readiness, TaskSequencer
from peel_nachi_bridge.task import TaskResult

LEARNER = "/model_learner_node"


def _sequencer(**node: object) -> tuple[TaskSequencer, list[tuple[str, str]]]:
    cfg = load_config({"node.tasks": 3, "node.wait_model_s": 30.0, **{f"node.{k}": v
                                                                        for k, v in node.items()}})
    logs: list[tuple[str, str]] = []
    return TaskSequencer(cfg.node, lambda level, text: logs.append((level, text))), logs


def _seen(updates: UpdateWait, version: int) -> Readiness:
    return Readiness(version, 5, 5, update_known=lambda k: updates.outcome(k) is not None)


def _done(index: int) -> TaskResult:
    return TaskResult(index, True, "done", "reached", "")


def _record(version: int, producer: str | None, task: int | None) -> ModelRecord:
    return ModelRecord(version=version, sha256=f"{version:064x}", path=f"m{version}.safetensors",
                       producer=producer, task=task)


def test_waits_for_the_learners_update_by_identity_not_by_number() -> None:
    seq, _ = _sequencer()
    updates = UpdateWait(LEARNER)
    updates.add_record(_record(0, None, None))
    assert seq.poll(0.0, _seen(updates, 0)) == 0
    seq.task_ended(1.0, _done(0), published=True)
    assert seq.poll(2.0, _seen(updates, 0)) is None
    updates.add_record(_record(1, None, None))  # swapped in from outside: not the update
    assert seq.poll(3.0, _seen(updates, 1)) is None
    updates.add_record(_record(2, LEARNER, 1))  # the learner's update after task 1
    assert seq.poll(4.0, _seen(updates, 2)) == 1


def test_a_failed_update_ends_the_wait_at_once_and_a_silent_one_after_the_timeout() -> None:
    seq, logs = _sequencer()
    updates = UpdateWait(LEARNER)
    updates.add_record(_record(0, None, None))
    assert seq.poll(0.0, _seen(updates, 0)) == 0
    seq.task_ended(1.0, _done(0), published=True)
    updates.add_report(UpdateReport(LEARNER, 1, FAILED, "probe batch: non-finite forces"))
    assert seq.poll(1.1, _seen(updates, 0)) == 1
    seq.task_ended(2.0, _done(1), published=True)
    assert seq.poll(20.0, _seen(updates, 0)) is None
    assert seq.poll(32.5, _seen(updates, 0)) == 2  # node.wait_model_s = 30 ran out
    assert any("update after task 2 did not arrive" in text for _, text in logs)


def test_no_wait_after_a_task_without_a_trajectory_or_with_the_wait_off() -> None:
    seq, _ = _sequencer()
    updates = UpdateWait(LEARNER)
    assert seq.poll(0.0, _seen(updates, 0)) == 0
    seq.task_ended(1.0, replace(_done(0), outcome="aborted"), published=False)
    assert seq.poll(1.1, _seen(updates, 0)) == 1  # the learner got nothing: nothing to wait for
    off, _ = _sequencer(wait_model_s=0.0)
    assert off.poll(0.0, _seen(updates, 0)) == 0
    off.task_ended(1.0, _done(0), published=True)
    assert off.poll(1.1, _seen(updates, 0)) == 1

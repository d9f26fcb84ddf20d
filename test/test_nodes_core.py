"""The nodes' work without ROS (no DDS needed): the simulator's task loop in lockstep, the
planner's state assembly and control loop, and the two driven against each other exactly as
the node graph drives them (docs/graph.md, "Time and lockstep")."""

from __future__ import annotations

import numpy as np
import pytest

from peel_model.checkpoint import load_checkpoint, shipped_checkpoint
from peel_msgs_py.errors import PeelError
from peel_msgs_py.task import task_seed
from peel_planner_node.config import load_planner_config
from peel_planner_node.control_loop import ControlLoop, StateAssembler
from peel_planner_node.dynamics import ReferenceDynamics
from peel_sim_node.config import load_sim_config
from peel_sim_node.lockstep import TaskSequence

SHORT = {"task.q_ter_mm": 4.0, "task.t_max_s": 6.0}


def _seq(**kw) -> TaskSequence:
    return TaskSequence(load_sim_config(SHORT), source="plant", seed=3, task_slot_s=20.0, **kw)


def test_task_sequence_lockstep_and_stamps() -> None:
    seq = _seq()
    first = seq.start(1)
    assert first.stamp_ns == 20_000_000_000 and first.task == 1 and seq.awaiting == first.stamp_ns
    assert seq.apply(first.stamp_ns + 1, 2.0) is None  # answers no waiting sample: ignored
    period = seq.apply(first.stamp_ns, 2.0)
    assert [s.stamp_ns - first.stamp_ns for s in period] == [k * 100_000_000 for k in range(1, 6)]
    assert seq.awaiting == period[-1].stamp_ns
    assert seq.apply(first.stamp_ns, 2.0) is None  # a repeated answer changes nothing
    while not seq.ended:
        seq.apply(seq.awaiting, 3.0)
    traj = seq.finish({"model_version": 4})
    assert traj.outcome in ("done", "timeout", "safety_stop") and seq.awaiting is None
    assert traj.meta["task_index"] == 1 and traj.meta["model_version"] == 4
    assert traj.meta["task_seed"] == task_seed(3, 1) and traj.meta["t0_ros_s"] == 20.0
    np.testing.assert_allclose(np.diff(traj.t), 0.1)
    seq.close()


def test_task_sequence_abort_and_bad_slot() -> None:
    seq = _seq()
    seq.start(0)
    traj = seq.finish({}, outcome="aborted")
    assert traj.outcome == "aborted" and len(traj) == 1
    seq.close()
    with pytest.raises(PeelError, match="task_slot_s"):
        TaskSequence(load_sim_config(SHORT), source="sim", seed=0, task_slot_s=5.0)


def test_state_assembler_completes_on_the_last_part_in_any_order() -> None:
    parts = StateAssembler()
    assert parts.add(10, 0, q_mm=1.0) is None
    assert parts.add(20, 0, fx_n=3.0, fz_n=4.0) is None  # another stamp interleaved
    assert parts.add(10, 0, fx_n=1.5, fz_n=-2.0) is None
    s = parts.add(10, 0, v_mmps=2.5)
    assert (s.stamp_ns, s.q_mm, s.v_mmps, s.fx_n, s.fz_n) == (10, 1.0, 2.5, 1.5, -2.0)
    assert list(parts.partial) == [20]
    for k in range(200):  # parts that never complete do not pile up
        parts.add(1000 + k, 0, q_mm=0.0)
    assert len(parts.partial) <= 51


def _loop() -> ControlLoop:
    cfg = load_planner_config().replace(**{"mppi.n_samples": 8, "mppi.horizon": 2,
                                           "task.q_ter_mm": 4.0, "task.t_max_s": 6.0})
    pred = load_checkpoint(shipped_checkpoint())
    return ControlLoop(cfg, ReferenceDynamics(pred, dt_s=cfg.cost.dt_s), seed=3)


def test_control_loop_and_task_sequence_in_lockstep() -> None:
    """The graph's protocol in one process: every control sample is answered with a command
    stamped with it, between control instants nothing is planned, re-sent samples get the same
    answer, and a new frame id starts a new task with a fresh planner."""
    loop, seq = _loop(), _seq()
    for task in (0, 1):
        sample = seq.start(task)
        answers = 0
        pending = [sample]
        while True:
            answer = None
            for s in pending:
                a = loop.on_sample(s)
                if a is not None and s.stamp_ns == seq.awaiting:
                    answer = a
            if answer is None:
                break
            assert answer.task == task and answer.u_mmps >= 0.0
            again = loop.on_sample(seq.last())  # the sim re-sends: the same answer
            assert again is not None and again.u_mmps == answer.u_mmps
            answers += 1
            pending = seq.apply(answer.stamp_ns, answer.u_mmps)
            if seq.ended:
                break
        traj = seq.finish({})
        assert loop.task == task and answers >= 2
        assert traj.outcome in ("done", "timeout", "safety_stop")
        assert loop.rows[0][0] == 0.0  # the task's own time restarts at 0
    seq.close()


def _commands(loop: ControlLoop) -> list[float]:
    """The commands of one task through the lockstep protocol."""
    seq, out = _seq(), []
    pending = [seq.start(0)]
    while not seq.ended:
        answers = [loop.on_sample(s) for s in pending]
        answer = next((a for a, s in zip(answers, pending, strict=True) if a is not None
                       and s.stamp_ns == seq.awaiting), None)
        if answer is None:
            break
        out.append(answer.u_mmps)
        pending = seq.apply(answer.stamp_ns, answer.u_mmps)
    seq.close()
    return out


def test_warm_up_plans_once_and_leaves_the_tasks_plans_unchanged() -> None:
    """The planner node's warm-up plan (before its first task) uses a planner of its own: the
    commands of the task that follows are the same as without it."""
    cold = _commands(_loop())
    warm_loop = _loop()
    seconds = warm_loop.warm_up(10)
    assert seconds > 0.0 and warm_loop.task == -1 and warm_loop.rows == []
    assert len(cold) >= 2 and _commands(warm_loop) == cold

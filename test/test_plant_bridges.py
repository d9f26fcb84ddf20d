"""Both plant bridges through their shared core (peel_bridge): the same test on the simulator
bridge (``peel_sim_node``) and on the Nachi bridge against the controller emulator.

Each bridge runs as a real process on its own ROS domain; a rig in the test process
(nachi_rig.Rig) stands in for the planner and the learner: it announces model v0 on
``/peel/model_version`` + ``/peel/model_info``, answers every control instant on
``/peel/cmd_vel``, records every topic to a bag, and after each trajectory announces the
learner's update of that task (v(k) after task k); before each command it sends the planner's
guard report (``/peel/planner_safety``). Checked on the bag: the topics, their stamps
(task k at k * node.task_slot_s + the plant's t, frame peel_task_<k>, /clock with them), the
trajectory message, model following (task 2 starts only after the update of task 1 and
records it as its model) and the same ``planner_guard`` and ``slowdown`` safety fields in both
bridges' meta.
"""

from __future__ import annotations

import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from graph_helpers import node_env
from nachi_rig import SLOT_S, Rig, bridge_cmd

from peel_bag import bagread
from peel_bridge.loop import TaskLoop
from peel_bridge.plant_node import PlantTopics
from peel_bridge.slowdown import SlowdownParams
from peel_msgs_py import topics
from peel_nachi_emulator.emulator import ControllerEmulator, EmulatorOptions
from peel_nachi_emulator.robot import Robot
from peel_planner_node.guard import GuardStats
from peel_sim_node.config import load_sim_config

pytestmark = pytest.mark.process  # starts processes or real-time I/O: scripts/flaky.sh

ROOT = Path(__file__).resolve().parents[1]
LEARNER = "/model_learner_node"
TASKS = 2
Q_TER_MM = 3.0
COMMON = {"node.tasks": TASKS, "node.exit_when_done": True, "node.wait_model_s": 60.0,
          "node.wait_planner_s": 60.0, "node.task_slot_s": SLOT_S}


def params(**values: object) -> list[str]:
    out = []
    for key, value in values.items():
        text = str(value).lower() if isinstance(value, bool) else str(value)
        out += ["-p", f"{key}:={text}"]
    return out


@pytest.fixture(params=["sim", "nachi"])
def bridge(request: pytest.FixtureRequest) -> Iterator[tuple[str, list[str]]]:
    """(name, command line) of one bridge; the Nachi bridge with an emulator in this process."""
    if request.param == "sim":
        yield "sim", [sys.executable, "-m", "peel_sim_node.node", "--ros-args", "--params-file",
                      str(ROOT / "config" / "peel_sim_node.yaml"),
                      *params(**COMMON, **{"task.q_ter_mm": Q_TER_MM, "node.seed": 3})]
        return
    cfg = load_sim_config({"task.q_ter_mm": Q_TER_MM})
    emu = ControllerEmulator(EmulatorOptions(port=0, speed=2.0, seed=3, source="sim"),
                             robot=Robot(source="sim", seed=3, cfg=cfg),
                             log=lambda text: None).start()
    try:
        yield "nachi", bridge_cmd(emu.port, **COMMON)
    finally:
        emu.close()


def follow_updates(rig: Rig) -> Callable[[], None]:
    """After trajectory k, announce the learner's update after task k as model v(k); returns
    the stop of the thread that does it."""
    stop = threading.Event()

    def run() -> None:
        announced = 0
        while not stop.is_set() and announced < TASKS:
            if len(rig.wait_trajectories(announced + 1, 0.2)) > announced:
                stop.wait(0.5)  # the bridge waits for it: task 2 must not start before
                announced += 1
                rig.announce(announced, LEARNER, announced)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return lambda: (stop.set(), thread.join(5.0))


def test_both_bridges_run_on_the_shared_core() -> None:
    from peel_nachi_bridge import node as nachi
    from peel_sim_node import node as sim

    assert sim.PlantTopics is nachi.PlantTopics is PlantTopics
    assert sim.TaskLoop is nachi.TaskLoop is TaskLoop


def test_topics_stamps_trajectory_and_model_following(bridge: tuple[str, list[str]],
                                                      tmp_path: Path, ros_domain: str) -> None:
    name, cmd = bridge
    rig = Rig(ros_domain, tmp_path / "bag", speed=lambda task, t: 4.0, guard_reports=True)
    stop = follow_updates(rig)
    try:
        out = subprocess.run(cmd, env=node_env(), capture_output=True, text=True, timeout=300)
    finally:
        stop()
        rig.close()
    assert out.returncode == 0, out.stderr[-3000:]
    assert "Traceback" not in out.stderr

    trajs = bagread.read_trajectories(tmp_path / "bag")
    assert len(trajs) == TASKS, name
    assert [t.outcome for t in trajs] == ["done"] * TASKS
    assert [t.meta["task_index"] for t in trajs] == list(range(TASKS))
    assert [t.meta["t0_ros_s"] for t in trajs] == [k * SLOT_S for k in range(TASKS)]
    assert [t.meta["model_version"] for t in trajs] == [0, 1]  # task 2 waited for v1
    assert trajs[1].meta["model_versions"] == [0, 1]
    assert all(t.meta["cmd_limits_mmps"] == [0.0, 20.0] for t in trajs)
    assert all(t.q[-1] >= Q_TER_MM for t in trajs)
    # the planner's guard: the same safety fields on both bridges, the task's last report
    assert rig.reports is not None
    for k, traj in enumerate(trajs):
        guard = traj.meta["planner_guard"]
        assert set(guard) == set(GuardStats().as_dict()), name
        sent = rig.reports[k]
        assert {"task": k, **guard} in sent  # one the planner sent for this task, the last
        assert guard["plans"] >= len(sent) - 1 >= 1  # or (a report racing the end) the one before
        assert guard["fallbacks"] == guard["plans"] // 3
        # the bridge's own slowdown zone (Eq. M6): the same fields, shipped off
        assert traj.meta["slowdown"] == {**SlowdownParams().zone(20.0).as_dict(),
                                         "samples": traj.meta["slowdown"]["samples"]}, name

    arrays = bagread.read_topics(tmp_path / "bag")
    w, tw, pose = arrays[topics.WRENCH], arrays[topics.TWIST], arrays[topics.POSE]
    for k, traj in enumerate(trajs):
        mine = w["task"] == k
        # every sample of the task once, stamped at the task's slot + the plant's t, in SI
        np.testing.assert_allclose(w["t_s"][mine], k * SLOT_S + traj.t, atol=1e-6)
        np.testing.assert_allclose(np.diff(w["t_s"][mine]), 0.1, atol=1e-6)
        np.testing.assert_allclose(w["fx_n"][mine], traj.fx, atol=1e-9)
        np.testing.assert_allclose(tw["v_mmps"][tw["task"] == k], traj.v, atol=1e-9)
        np.testing.assert_allclose(pose["q_mm"][pose["task"] == k], traj.q, atol=1e-9)
    assert set(w["task"]) == set(range(TASKS))
    clock = arrays[topics.CLOCK]["t_s"]  # best effort, depth 1: may skip, never goes back
    assert len(clock) >= 2 and np.all(np.diff(clock) >= 0)
    assert np.all(np.min(np.abs(clock[:, None] - w["t_s"][None, :]), axis=1) < 1e-6)
    assert float(np.max(pose["q_mm"])) < 10.0

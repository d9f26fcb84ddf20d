"""The ``node.*`` parameters of the task loop, declared alike by both plant bridges
(``peel_sim_node``, ``peel_nachi_bridge``; docs/graph.md), as plain data (no ROS).

Every timeout is wall time; ``node.task_slot_s`` is ROS time (task k starts at k times it,
:func:`peel_bridge.loop.task_stamp_ns`).
"""

from __future__ import annotations

from peel_msgs_py.params import ParamSpec

#: The task sequence: how many tasks, their ROS time slot, what to wait for before and between.
LOOP_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("node.tasks", int, 3, "consecutive tasks to run; 0 = until stopped", min=0),
    ParamSpec("node.task_slot_s", float, 100.0,
              "ROS time reserved per task, s (> the task's t_max)", min=1.0),
    ParamSpec("node.wait_model_s", float, 120.0,
              "wall s to wait for the learner's new model between tasks; 0 = do not", min=0.0),
    ParamSpec("node.learner_node", str, "/model_learner_node",
              "the learner whose update of the last task is waited for, by its identity "
              "(/peel/model_info, /peel/model_update; docs/graph.md)"),
    ParamSpec("node.wait_planner_s", float, 120.0,
              "wall s to wait for the planner's /peel/model_info and the readers before task 1",
              min=0.0),
    ParamSpec("node.min_subscribers", int, 1,
              "wait for this many subscribers of each state topic before task 1 (planner, "
              "recorder)", min=0),
    ParamSpec("node.min_traj_subscribers", int, 1,
              "wait for this many subscribers of /peel/trajectory before task 1 (learner, "
              "launcher, recorder)", min=0),
    ParamSpec("node.exit_when_done", bool, False,
              "exit after the last task (and its model update); for ros2 launch"),
)

"""Every parameter ``peel_sim_node`` declares, as plain data (no ROS): the library's groups
(:data:`peel_sim_node.config.SPECS`: task, scene, randomization, compensation, noise, plant) and
the node's own ``node.*`` group (wall-clock timeouts, the task sequence; docs/graph.md).

Registered under the ``peel.parameters`` entry point, so every parameter file naming this node
is checked against it (:func:`peel_msgs_py.params.load_param_file`). All of them are read-only
at run time: the physics and the task sequence are fixed when the node starts.
"""

from __future__ import annotations

from peel_msgs_py.params import USE_SIM_TIME, ParamSpec
from peel_msgs_py.wire import speed_limit_specs

from .config import SPECS as LIBRARY_SPECS

NODE_NAME = "peel_sim_node"

#: Node-only parameters (``node:`` group of config/peel_sim_node.yaml); wall-clock timeouts.
NODE_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("node.source", str, "sim", "run the simulator or the plant", choices=("sim", "plant")),
    ParamSpec("node.tasks", int, 3, "consecutive tasks to run; 0 = until stopped", min=0),
    ParamSpec("node.seed", int, 0, "seed of the task sequence (as peel experiment's)", min=0),
    ParamSpec("node.task_slot_s", float, 100.0, "ROS time reserved per task, s", min=1.0),
    ParamSpec("node.cmd_timeout_s", float, 2.0, "wall s before the sample is re-sent", min=0.01),
    ParamSpec("node.cmd_give_up_s", float, 120.0, "wall s before the task is aborted", min=0.1),
    ParamSpec("node.wait_model_s", float, 120.0,
              "wall s to wait for the learner's new model between tasks; 0 = do not", min=0.0),
    ParamSpec("node.learner_node", str, "/model_learner_node",
              "the learner whose update after each task is waited for (by identity)"),
    ParamSpec("node.wait_planner_s", float, 120.0,
              "wall s to wait for the planner's /peel/model_info before task 1", min=0.0),
    ParamSpec("node.min_subscribers", int, 1,
              "wait for this many subscribers of each state topic before task 1", min=0),
    ParamSpec("node.min_traj_subscribers", int, 1,
              "wait for this many subscribers of /peel/trajectory before task 1 (learner, "
              "launcher, recorder)", min=0),
    *speed_limit_specs("node", "executed"),
    ParamSpec("node.exit_when_done", bool, False,
              "exit after the last task (and its model update); for ros2 launch"),
    ParamSpec("node.effects", list, [""],
              "user effects added to the plant, each 'module:function' "
              "(peel_sim_node.effects; docs/residual.md); [''] or [] = none"),
)

#: Everything the node declares.
SPECS: tuple[ParamSpec, ...] = (*LIBRARY_SPECS, *NODE_SPECS, USE_SIM_TIME)

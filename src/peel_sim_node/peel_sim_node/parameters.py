"""Every parameter ``peel_sim_node`` declares, as plain data (no ROS): the library's groups
(:data:`peel_sim_node.config.SPECS`: task, scene, randomization, compensation, noise, plant) and
the node's own ``node.*`` group (wall-clock timeouts, the task sequence; docs/graph.md).

Registered under the ``peel.parameters`` entry point, so every parameter file naming this node
is checked against it (:func:`peel_msgs_py.params.load_param_file`). All of them are read-only
at run time: the physics and the task sequence are fixed when the node starts.
"""

from __future__ import annotations

from peel_bridge.parameters import LOOP_SPECS
from peel_msgs_py.lifecycle import AUTOSTART
from peel_msgs_py.params import USE_SIM_TIME, ParamSpec
from peel_msgs_py.wire import speed_limit_specs

from .config import SPECS as LIBRARY_SPECS

NODE_NAME = "peel_sim_node"

#: Node-only parameters (``node:`` group of config/peel_sim_node.yaml): the plant, the lockstep's
#: wall-clock timeouts, the task loop's (:data:`peel_bridge.parameters.LOOP_SPECS`), the limits.
NODE_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("node.source", str, "sim", "run the simulator or the plant", choices=("sim", "plant")),
    ParamSpec("node.seed", int, 0, "seed of the task sequence (as peel experiment's)", min=0),
    ParamSpec("node.cmd_timeout_s", float, 2.0, "wall s before the sample is re-sent", min=0.01),
    ParamSpec("node.cmd_give_up_s", float, 120.0, "wall s before the task is aborted", min=0.1),
    ParamSpec("node.real_time_factor", float, 0.0,
              "simulated s per wall s at most (1 = real time, as on the robot; 0 = as fast as "
              "the planner answers)", min=0.0, max=1000.0),
    *LOOP_SPECS,
    *speed_limit_specs("node", "executed"),
    ParamSpec("node.effects", list, [""],
              "user effects added to the plant, each 'module:function' "
              "(peel_sim_node.effects; docs/residual.md); [''] or [] = none"),
    AUTOSTART,
)

#: Everything the node declares.
SPECS: tuple[ParamSpec, ...] = (*LIBRARY_SPECS, *NODE_SPECS, USE_SIM_TIME)

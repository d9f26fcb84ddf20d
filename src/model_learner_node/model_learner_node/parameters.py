"""Every parameter ``model_learner_node`` declares, as plain data (no ROS): the model
architecture (3.1), offline training (Eq. 23-25), MAML (Eq. 26-27, Algorithm 1), baseline 2
and the node's own ``node.*`` group. Registered under the ``peel.parameters`` entry point, so
``peel train`` and the node refuse the same unknown names. All read-only at run time. (No torch
here: every command that reads a parameter file may load it.)
"""

from __future__ import annotations

from peel_model.config import MODEL_SPECS
from peel_msgs_py.params import USE_SIM_TIME, ParamSpec

from .config import BASELINE2_SPECS, GATE_SPECS, MAML_SPECS, ONLINE_SPECS, TRAIN_SPECS

NODE_NAME = "model_learner_node"

#: Node-only parameters (``node:`` group of config/model_learner_node.yaml).
NODE_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("node.init_model", str, "", "checkpoint to start from; empty = the shipped one"),
    ParamSpec("node.out_dir", str, "runs/models", "where model_vNNNN.safetensors are written"),
    ParamSpec("node.resume", bool, True,
              "go on from the learner state in node.out_dir (learner_state.safetensors: "
              "weights, replay pool, meta-optimiser) when there is one"),
    ParamSpec("node.method", str, "maml", "maml = Algorithm 1; retrain = baseline 2",
              choices=("maml", "retrain")),
    ParamSpec("node.planner_node", str, "peel_planner_node",
              "node whose model.path is set; relative = in the learner's namespace"),
    ParamSpec("node.swap_timeout_s", float, 60.0, "wall s to wait for the swap answer", min=0.1),
    ParamSpec("node.pool_capacity", int, 0, "replay pool size in trajectories; 0 = all", min=0),
    ParamSpec("node.threads", int, 1, "torch CPU threads of the learner process", min=1),
    ParamSpec("node.cells", list, [""],
              "namespaces of the cells served (docs/fleet.md), e.g. ['/cell_0', '/cell_1']; "
              "[''] or [] = the one cell of the learner's own namespace"),
    ParamSpec("node.cell_wait_s", float, 30.0,
              "wall s a finished task waits for an earlier one of another cell (task order)",
              min=0.0),
)


#: Everything the node declares.
SPECS: tuple[ParamSpec, ...] = (*MODEL_SPECS, *TRAIN_SPECS, *MAML_SPECS, *GATE_SPECS, *ONLINE_SPECS,
                                 *BASELINE2_SPECS,
                                 *NODE_SPECS, USE_SIM_TIME)

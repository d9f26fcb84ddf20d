"""Every parameter ``peel_planner_node`` declares, as plain data (no ROS): the planner library's
groups (:data:`peel_planner_node.config.PARAM_SPECS`: task, cost Eq. 3-5, mppi Algorithm 2,
safety), the swap parameter ``model.path`` and the node's own ``node.*`` group.

Registered under the ``peel.parameters`` entry point. At run time ``model.path`` (the model
swap, docs/graph.md) and the cost weights and a few MPPI settings (:data:`DYNAMIC`, applied from
the next task on) accept new values; everything else is read-only.
"""

from __future__ import annotations

from dataclasses import replace

from peel_msgs_py.lifecycle import AUTOSTART
from peel_msgs_py.params import USE_SIM_TIME, ParamSpec

from .config import PARAM_SPECS as LIBRARY_SPECS

NODE_NAME = "peel_planner_node"
MODEL_PATH = "model.path"

#: Library parameters a running planner accepts (from the next task on).
DYNAMIC: frozenset[str] = frozenset({
    "mppi.lambda", "mppi.n_samples", "mppi.horizon", "mppi.sigma0", "mppi.noise_correlation",
    "mppi.control_cost_scale",
})

#: Node-only parameters (``node:`` and ``model:`` groups of config/peel_planner_node.yaml).
NODE_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec(MODEL_PATH, str, "", "forward model checkpoint (.safetensors) to plan with; empty "
              "= the shipped one; setting it swaps the model (validated first)", dynamic=True),
    ParamSpec("node.probe_batch", int, 16, "rows of the probe batch run on a new model", min=1),
    ParamSpec("node.threads", int, 1, "torch CPU threads of the planner process", min=1),
    ParamSpec("node.seed", int, 0, "seed of the task sequence; task k plans with mppi.seed = "
              "task_seed(seed, k) as peel experiment does", min=0),
    ParamSpec("node.min_cmd_subscribers", int, 1,
              "readers of /peel/cmd_vel (simulator, recorder) to wait for before announcing the "
              "model version (the simulator starts on it)", min=0),
    ParamSpec("node.wait_subscribers_s", float, 60.0,
              "wall s to wait for them; then the version is announced anyway", min=0.0),
    AUTOSTART,
)

#: Everything the node declares.
SPECS: tuple[ParamSpec, ...] = (
    *(replace(s, dynamic=s.name.startswith("cost.") or s.name in DYNAMIC)
      for s in LIBRARY_SPECS),
    *NODE_SPECS, USE_SIM_TIME,
)

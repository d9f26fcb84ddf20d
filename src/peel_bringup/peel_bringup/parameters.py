"""Every parameter of the ``peel_bringup`` section (config/peel_bringup.yaml), as plain data:
the launcher's ``graph.*`` group (``peel graph``, ``peel demo``) and the experiments'
``experiment.*`` and ``sweep.*`` groups. Registered under the ``peel.parameters`` entry point.
"""

from __future__ import annotations

from peel_msgs_py.params import ParamSpec

NODE_NAME = "peel_bringup"

#: The ``graph:`` group.
GRAPH_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("graph.tasks", int, 3, "consecutive tasks K", min=1),
    ParamSpec("graph.plant", str, "sim",
              "sim, plant, or nachi (the Nachi robot controller, docs/nachi.md)",
              choices=("sim", "plant", "nachi")),
    ParamSpec("graph.seed", int, 0, "seed of the task sequence", min=0),
    ParamSpec("graph.out_dir", str, "runs/graph", "parent of the run directories"),
    ParamSpec("graph.final_model_wait_s", float, 300.0,
              "wall s to wait for the learner's swap after the last task", min=0.0),
    ParamSpec("graph.stop_timeout_s", float, 20.0,
              "wall s a node gets to exit after SIGINT before SIGTERM / SIGKILL", min=0.1),
    ParamSpec("graph.alone_wait_s", float, 5.0,
              "wall s of DDS discovery before the start, looking for another peel graph on "
              "the ROS domain (found: refused, exit 5)", min=0.0),
    ParamSpec("graph.lifecycle_timeout_s", float, 180.0,
              "wall s for a managed node's change_state service to appear and answer "
              "(configure loads the model, builds the simulator, connects the controller)",
              min=1.0, max=3600.0),
)


def _specs() -> tuple[ParamSpec, ...]:
    from peel_experiments.experiment_config import EXPERIMENT_SPECS

    return (*GRAPH_SPECS, *EXPERIMENT_SPECS)


def __getattr__(name: str) -> tuple[ParamSpec, ...]:
    """``SPECS`` on first use (the experiment groups live in :mod:`peel_experiments.experiment`)."""
    if name == "SPECS":
        return _specs()
    raise AttributeError(name)

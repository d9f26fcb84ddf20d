"""``model_learner_node``: online learning of the forward model as a ROS 2 node (issue 7).

* Subscribes ``/peel/trajectory`` (trajectory codec) and keeps the whole trajectories in a
  :class:`~model_learner_node.replay.ReplayPool` (3.3.1).
* After each task runs Algorithm 1 (:meth:`model_learner_node.maml.MetaLearner.update`,
  Eq. 26-27; or baseline 2, ``node.method: retrain``) in a worker thread, so the callbacks (and
  the planner, another process) never wait for it.
* Writes each updated model atomically as ``node.out_dir/model_vNNNN.safetensors`` (+ JSON,
  :func:`~model_learner_node.checkpoint.save_checkpoint`: temporary file + ``os.replace``;
  safetensors only, never a pickle) and then asks the planner to swap it in by setting the
  planner's ``model.path`` parameter through its SetParameters service. A refused swap is
  logged with the planner's reason; the learner keeps training its own copy.

The node is a thin adapter: the learning is the library's (:mod:`model_learner_node.maml`).
"""

from __future__ import annotations

import json
import math
import queue
import re
import sys
import threading
from pathlib import Path
from typing import Any

import torch

from peel_msgs_py.errors import PeelError
from peel_msgs_py.params import ParamSpec, validate_group

NODE_NAME = "model_learner_node"
_VERSION_RE = re.compile(r"model_v(\d+)")

#: Node-only parameters (``node:`` group of config/model_learner_node.yaml).
NODE_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("node.init_model", str, "", "checkpoint to start from; empty = the shipped one"),
    ParamSpec("node.out_dir", str, "runs/models", "where model_vNNNN.safetensors are written"),
    ParamSpec("node.method", str, "maml", "maml = Algorithm 1; retrain = baseline 2",
              choices=("maml", "retrain")),
    ParamSpec("node.planner_node", str, "/peel_planner_node", "node whose model.path is set"),
    ParamSpec("node.swap_timeout_s", float, 60.0, "wall s to wait for the swap answer", min=0.1),
    ParamSpec("node.pool_capacity", int, 0, "replay pool size in trajectories; 0 = all", min=0),
    ParamSpec("node.threads", int, 1, "torch CPU threads of the learner process", min=1),
)


def node_params(flat: dict[str, Any]) -> dict[str, Any]:
    """Validate the ``node.*`` parameters (others are ignored)."""
    return validate_group(NODE_SPECS, flat, "node")


def all_parameters(node: Any) -> dict[str, Any]:
    """Every declared parameter of ``node`` as a flat ``name -> value`` dict (rclpy API)."""
    return {name: p.value for name, p in node.get_parameters_by_prefix("").items()}


def json_safe(obj: Any) -> Any:
    """``obj`` with non-finite floats as None and unknown objects as strings (checkpoint meta)."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if obj is None or isinstance(obj, (bool, int, str)):
        return obj
    return json.loads(json.dumps(obj, default=str)) if not hasattr(obj, "item") else \
        json_safe(obj.item())


def model_file(out_dir: Path, version: int) -> Path:
    """``out_dir/model_vNNNN.safetensors``."""
    return out_dir / f"model_v{version:04d}.safetensors"


class LearnerNode:
    """The node object (run from :func:`main`)."""

    def __init__(self) -> None:
        from peel_msgs_py import codec, topics
        from peel_msgs_py.runtime import Node
        from peel_msgs_py.runtime.msg import Float64MultiArray
        from peel_msgs_py.runtime.srv import SetParameters

        from .checkpoint import load_checkpoint, shipped_checkpoint
        from .replay import ReplayPool

        self.codec = codec
        self.node = n = Node(NODE_NAME, automatically_declare_parameters_from_overrides=True)
        flat = all_parameters(n)
        self.p = node_params(flat)
        torch.set_num_threads(self.p["node.threads"])
        self.log = n.get_logger()
        init = self.p["node.init_model"]
        init_path = shipped_checkpoint() if not init else Path(init)
        self.predictor = load_checkpoint(init_path)
        m = _VERSION_RE.search(init_path.name)
        self.version = int(m.group(1)) if m else 0
        if self.p["node.method"] == "maml":
            from .maml import MamlConfig, MetaLearner

            self.learner = MetaLearner(self.predictor, MamlConfig.from_params(flat))
        else:
            from .baselines2 import Baseline2Config, HistoryRetrainer

            self.learner = HistoryRetrainer(self.predictor, Baseline2Config.from_params(flat))
        cap = self.p["node.pool_capacity"]
        self.pool = ReplayPool(capacity=cap or None)
        self.out_dir = Path(self.p["node.out_dir"])
        self.out_dir.mkdir(parents=True, exist_ok=True)
        service = self.p["node.planner_node"].rstrip("/") + "/set_parameters"
        self.client = n.create_client(SetParameters, service)
        self.SetParameters = SetParameters
        self.queue: queue.Queue[Any] = queue.Queue()
        self.n_tasks = 0
        n.create_subscription(Float64MultiArray, topics.TRAJECTORY, self._on_trajectory,
                              topics.qos_profile(topics.TRAJECTORY, subscriber=True))
        self.worker = threading.Thread(target=self._work, name="algorithm1", daemon=True)
        self.worker.start()
        self.log.info(f"learner ready: {self.p['node.method']} from {init_path.name} "
                      f"(v{self.version}), writing to {self.out_dir}")

    # -- callbacks ---------------------------------------------------------------------------
    def _on_trajectory(self, msg: Any) -> None:
        try:
            traj = self.codec.trajectory_from_msg(msg)
        except PeelError as exc:
            self.log.error(f"ignoring a malformed /peel/trajectory message: {exc}")
            return
        self.queue.put(traj)

    # -- worker ------------------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            traj = self.queue.get()
            if traj is None:
                return
            try:
                self.learn(traj)
            except Exception as exc:  # keep the node alive; the planner keeps its model
                self.log.error(f"update after task {self.n_tasks} failed: "
                               f"{type(exc).__name__}: {exc}")

    def learn(self, traj: Any) -> None:
        """Algorithm 1 on one finished task, then write and swap the new weights."""
        from .checkpoint import save_checkpoint

        self.n_tasks += 1
        report = self.learner.update(traj, self.pool)
        self.pool.add(traj)
        if not report.get("updated", True):
            self.log.warn(f"task {self.n_tasks}: no update ({report.get('reason', '')})")
            return
        self.version += 1
        meta = {"version": self.version, "task": self.n_tasks,
                "task_meta": traj.meta, "update": report}
        meta = json_safe(meta)
        path = save_checkpoint(model_file(self.out_dir, self.version), self.predictor, meta)
        self.log.info(f"task {self.n_tasks}: Algorithm 1 done in {report.get('update_s', 0):.2f} s"
                      f", wrote {path.name}")
        ok, reason = self.request_swap(path)
        if ok:
            self.log.info(f"planner swapped to v{self.version}")
        else:
            self.log.warn(f"planner refused v{self.version}: {reason}")

    def request_swap(self, path: Path) -> tuple[bool, str]:
        """Set the planner's ``model.path`` via SetParameters; wait (this thread) for the answer."""
        from peel_msgs_py.runtime.msg import Parameter, ParameterType, ParameterValue

        timeout = self.p["node.swap_timeout_s"]
        if not self.client.wait_for_service(timeout_sec=timeout):
            return False, f"service {self.client.srv_name} not available after {timeout:g} s"
        req = self.SetParameters.Request()
        req.parameters = [Parameter(name="model.path", value=ParameterValue(
            type=ParameterType.PARAMETER_STRING, string_value=str(path.resolve())))]
        done = threading.Event()
        future = self.client.call_async(req)
        future.add_done_callback(lambda _f: done.set())
        if not done.wait(timeout):
            return False, f"no answer from the planner within {timeout:g} s"
        resp = future.result()
        if resp is None or not resp.results:
            return False, "empty answer"
        res = resp.results[0]
        return bool(res.successful), str(getattr(res, "reason", ""))

    def close(self) -> None:
        self.queue.put(None)
        self.node.destroy_node()


def main(args: list[str] | None = None) -> int:
    """Console entry point ``model_learner_node`` (``--ros-args --params-file ... -p ...``)."""
    from peel_msgs_py.runtime import rclpy
    from peel_msgs_py.runtime.entry import run_node

    def spin(node: LearnerNode) -> None:
        while rclpy.ok():
            rclpy.spin_once(node.node, timeout_sec=0.1)

    return run_node(NODE_NAME, lambda argv: LearnerNode(), spin, args)


if __name__ == "__main__":
    sys.exit(main())

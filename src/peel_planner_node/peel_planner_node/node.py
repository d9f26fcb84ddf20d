"""``peel_planner_node``: OL-MPPI as a ROS 2 node (issue 7, docs/graph.md).

* Subscribes ``/peel/wrench``, ``/peel/twist``, ``/peel/pose`` (SI) and assembles, per task, the
  measured history (:class:`~peel_msgs_py.trajectory.Trajectory`, paper units).
* Plans once per control period of ROS time (every 5th sample of 0.1 s = 2 Hz; simulated time
  from ``/clock`` when ``use_sim_time`` is set): :meth:`peel_planner_node.mppi.Planner.plan`
  (Algorithm 2), which returns 0 (blade stopped) on the 20 N prewarning, t > t_max or q_ter
  (:class:`~peel_planner_node.safety.SafetyMonitor`, section 4.2). The command goes out on
  ``/peel/cmd_vel`` stamped with the stamp of the state sample it answers (lockstep).
* Holds the forward model. The model swap is the node's standard parameter service: setting
  ``model.path`` to a safetensors checkpoint runs the on-set-parameters callback, which loads it
  with :func:`~model_learner_node.checkpoint.load_checkpoint` (format, shapes, config, finite
  tensors; never a pickle), runs a probe batch (finite outputs required) and either swaps it in
  between two planning cycles (same lock) or refuses with the reason, keeping the old model.
* Publishes the active model version on ``/peel/model_version`` (Int64, transient local).

A new task is recognised by the ``header.frame_id`` of the state (``peel_task_<k>``,
:func:`peel_msgs_py.codec.task_frame_id`); a re-sent sample (same stamp) is answered with the
command already computed for it.
"""

from __future__ import annotations

import re
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import torch

from peel_msgs_py.errors import CheckpointError, PeelError
from peel_msgs_py.params import ParamSpec, validate_group
from peel_msgs_py.trajectory import Trajectory
from peel_msgs_py.units import m_to_mm, mmps_to_mps, mps_to_mmps

NODE_NAME = "peel_planner_node"
MODEL_PATH = "model.path"
_VERSION_RE = re.compile(r"model_v(\d+)")

#: Node-only parameters (``node:`` group of config/peel_planner_node.yaml).
NODE_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("node.probe_batch", int, 16, "rows of the probe batch run on a new model", min=1),
    ParamSpec("node.threads", int, 1, "torch CPU threads of the planner process", min=1),
    ParamSpec("node.seed", int, 0, "seed of the task sequence; task k plans with mppi.seed = "
              "task_seed(seed, k) as peel experiment does", min=0),
)


def node_params(flat: dict[str, Any]) -> dict[str, Any]:
    """Validate the ``node.*`` parameters (others are ignored)."""
    return validate_group(NODE_SPECS, flat, "node")


def all_parameters(node: Any) -> dict[str, Any]:
    """Every declared parameter of ``node`` as a flat ``name -> value`` dict (rclpy API)."""
    return {name: p.value for name, p in node.get_parameters_by_prefix("").items()}


def resolve_model_path(value: str) -> Path:
    """``model.path``: empty = the shipped checkpoint."""
    from model_learner_node.checkpoint import shipped_checkpoint

    return shipped_checkpoint() if not value else Path(value)


def version_of(path: Path, fallback: int) -> int:
    """Model version from a ``model_vNNNN`` file name, else ``fallback``."""
    m = _VERSION_RE.search(path.name)
    return int(m.group(1)) if m else fallback


def validate_model(path: Path, probe_rows: np.ndarray | None, batch: int, h_ref: int | None) -> Any:
    """Load and check a checkpoint for the swap; returns the predictor or raises PeelError.

    Checks: :func:`load_checkpoint` (safetensors + JSON: format, architecture, tensor names,
    shapes, dtypes, checksum, finite values), history length ``h`` equal to the running model's
    (``h_ref``), and finite outputs on a probe batch built from the latest measured rows (or a
    fixed synthetic one before the first sample).
    """
    from model_learner_node.checkpoint import load_checkpoint

    if path.suffix not in (".safetensors", ""):
        raise CheckpointError(f"model.path must name a .safetensors checkpoint, got {path.name}")
    pred = load_checkpoint(path)
    h = int(pred.h)
    if h_ref is not None and h != h_ref:
        raise CheckpointError(f"model history h = {h} differs from the running model's {h_ref}")
    if probe_rows is None or len(probe_rows) == 0:
        probe_rows = np.array([[5.0, 1.0, 2.0, 2.0]])
    rows = probe_rows[-h:]
    if len(rows) < h:
        rows = np.concatenate([np.repeat(rows[:1], h - len(rows), axis=0), rows])
    dtype = next(pred.parameters()).dtype
    hist = torch.as_tensor(rows, dtype=dtype).expand(batch, h, 4).clone()
    v_next = torch.linspace(0.0, 8.0, batch, dtype=dtype)
    with torch.inference_mode():
        out = pred.predict(hist, v_next)
    if tuple(out.shape) != (batch, 2):
        raise CheckpointError(f"probe batch: model output has shape {tuple(out.shape)}, "
                              f"expected {(batch, 2)}")
    if not bool(torch.isfinite(out).all()):
        raise CheckpointError("probe batch: the model predicts non-finite forces")
    return pred


class PlannerNode:
    """The node object (run from :func:`main`)."""

    def __init__(self) -> None:
        from peel_msgs_py import codec, topics
        from peel_msgs_py.runtime import Node
        from peel_msgs_py.runtime.msg import Int64, PoseStamped, TwistStamped, WrenchStamped

        from .config import PlannerConfig
        from .cost import Cost
        from .dynamics import learned_dynamics
        from .mppi import Planner

        self.topics, self.codec = topics, codec
        self.Int64, self.TwistStamped = Int64, TwistStamped
        self.node = n = Node(NODE_NAME, automatically_declare_parameters_from_overrides=True)
        if not n.has_parameter(MODEL_PATH):
            n.declare_parameter(MODEL_PATH, "")
        flat = all_parameters(n)
        self.p = node_params(flat)
        torch.set_num_threads(self.p["node.threads"])
        self.cfg = PlannerConfig.from_params(flat)
        self.dt = float(self.cfg.cost.dt_s)
        self.dt_ns = round(self.dt * 1e9)
        self.steps = self.cfg.mppi.steps_per_horizon_step
        self.log = n.get_logger()
        self.learned_dynamics = learned_dynamics

        path = resolve_model_path(str(flat.get(MODEL_PATH) or ""))
        pred = validate_model(path, None, self.p["node.probe_batch"], None)
        self.h = int(pred.h)
        self.version = version_of(path, 0)
        self.model_path = path
        self.Planner, self.cost = Planner, Cost(self.cfg.cost)
        self.planner = Planner(learned_dynamics(pred, self.cfg.dynamics), self.cost, self.cfg)
        self.lock = threading.Lock()

        qos = topics.qos_profile
        self.pub_cmd = n.create_publisher(TwistStamped, topics.CMD_VEL, qos(topics.CMD_VEL))
        self.pub_version = n.create_publisher(Int64, topics.MODEL_VERSION,
                                              qos(topics.MODEL_VERSION))
        self.parts: dict[int, dict[str, float]] = {}
        self.rows: list[list[float]] = []  # t, q, v, u, fx, fz, psi of the current task
        self.t0_ns: int | None = None
        self.last_ns: int | None = None
        self.answered: dict[int, float] = {}
        self.u_hold = 0.0
        self.task = -1
        self.cycles = 0
        n.create_subscription(WrenchStamped, topics.WRENCH, self._on_wrench,
                              qos(topics.WRENCH, subscriber=True))
        n.create_subscription(TwistStamped, topics.TWIST, self._on_twist,
                              qos(topics.TWIST, subscriber=True))
        n.create_subscription(PoseStamped, topics.POSE, self._on_pose,
                              qos(topics.POSE, subscriber=True))
        n.add_on_set_parameters_callback(self._on_set_parameters)
        self.publish_version()
        self.log.info(f"planner ready: model v{self.version} ({path.name}), "
                      f"N={self.cfg.mppi.n_samples}, H={self.cfg.mppi.horizon}, "
                      f"{self.planner.dynamics.describe()}")

    # -- model swap --------------------------------------------------------------------------
    def close(self) -> None:
        self.node.destroy_node()

    def publish_version(self) -> None:
        msg = self.Int64()
        msg.data = int(self.version)
        self.pub_version.publish(msg)

    def _on_set_parameters(self, params: list[Any]) -> Any:
        from peel_msgs_py.runtime import SetParametersResult

        for param in params:
            if param.name != MODEL_PATH:
                return SetParametersResult(
                    successful=False, reason=f"parameter '{param.name}' is read-only at run time")
        for param in params:
            value = param.value
            if not isinstance(value, str) or not value:
                return SetParametersResult(
                    successful=False, reason="model.path must be a non-empty string")
            path = Path(value)
            try:
                with self.lock:
                    probe = np.asarray(self.rows, dtype=np.float64)[:, [1, 2, 4, 5]] \
                        if self.rows else None
                pred = validate_model(path, probe, self.p["node.probe_batch"], self.h)
            except PeelError as exc:
                reason = f"model swap refused: {exc}"
                self.log.warn(reason)
                return SetParametersResult(successful=False, reason=reason)
            except Exception as exc:  # anything else a broken file can raise
                reason = f"model swap refused: {type(exc).__name__}: {exc}"
                self.log.warn(reason)
                return SetParametersResult(successful=False, reason=reason)
            with self.lock:  # atomic between two planning cycles
                self.planner.set_dynamics(self.learned_dynamics(pred, self.cfg.dynamics))
                self.version = version_of(path, self.version + 1)
                self.model_path = path
            self.publish_version()
            self.log.info(f"model swap: now v{self.version} ({path.name})")
        return SetParametersResult(successful=True, reason="")

    # -- state assembly ----------------------------------------------------------------------
    def _part(self, msg: Any, key: str, value: float) -> None:
        s = msg.header.stamp
        stamp = int(s.sec) * 1_000_000_000 + int(s.nanosec)
        d = self.parts.setdefault(stamp, {})
        d[key] = value
        if len(d) == 4:
            del self.parts[stamp]
            try:
                task = self.codec.task_from_frame_id(msg.header.frame_id)
            except PeelError as exc:
                self.log.error(f"ignoring a state sample: {exc}")
                return
            self.on_sample(stamp, d, task)
        if len(self.parts) > 50:  # incomplete leftovers
            for k in sorted(self.parts)[:-20]:
                del self.parts[k]

    def _on_wrench(self, msg: Any) -> None:
        f = msg.wrench.force
        s = msg.header.stamp
        stamp = int(s.sec) * 1_000_000_000 + int(s.nanosec)
        d = self.parts.setdefault(stamp, {})
        d["fx"] = float(f.x)
        self._part(msg, "fz", float(f.z))

    def _on_twist(self, msg: Any) -> None:
        self._part(msg, "v", float(mps_to_mmps(msg.twist.linear.x)))

    def _on_pose(self, msg: Any) -> None:
        self._part(msg, "q", float(m_to_mm(msg.pose.position.x)))

    def on_sample(self, stamp: int, d: dict[str, float], task: int) -> None:
        """A complete state sample arrived: extend the history; plan at a control instant."""
        if self.last_ns is not None and stamp <= self.last_ns:
            if stamp in self.answered:  # the sim re-sent a sample: repeat the answer
                self.publish_cmd(stamp, self.answered[stamp])
            return
        if task != self.task:
            self.new_task(task, stamp)
        self.last_ns = stamp
        t = (stamp - self.t0_ns) / 1e9
        self.rows.append([t, d["q"], d["v"], self.u_hold, d["fx"], d["fz"], float("nan")])
        k = round((stamp - self.t0_ns) / self.dt_ns)
        if k % self.steps == 0:
            self.plan_cycle(stamp)
        elif self.planner.stop is None:
            # between control instants: the 20 N prewarning / t_max stop the blade at once
            with self.lock:
                stop = self.planner.safety.check_sample(t, d["q"], d["fx"], d["fz"])
            if stop is not None and stop.reason != "done":
                self.log.info(f"task {self.task + 1}: blade stopped ({stop.reason} at "
                              f"t={stop.t:.1f} s, between control instants)")
                self.answered[stamp] = 0.0
                self.publish_cmd(stamp, 0.0)

    def new_task(self, task: int, stamp: int) -> None:
        seed = int(np.random.SeedSequence([self.p["node.seed"], 0, task]).generate_state(1)[0])
        cfg = self.cfg.replace(**{"mppi.seed": seed % (2**31)})
        with self.lock:
            self.task = task
            self.t0_ns = stamp
            self.rows = []
            self.answered = {}
            self.u_hold = 0.0
            # a fresh planner per task with the current model, as peel experiment does
            self.planner = self.Planner(self.planner.dynamics, self.cost, cfg)
            self.planner.reset()
        self.log.info(f"task {self.task + 1} starts at ROS time {stamp / 1e9:.1f} s "
                      f"(model v{self.version})")

    def plan_cycle(self, stamp: int) -> None:
        """One OL-MPPI cycle on the history up to the sample ``stamp``."""
        with self.lock:
            history = Trajectory.from_array(np.asarray(self.rows, dtype=np.float64))
            was_stopped = self.planner.stop is not None
            u = float(self.planner.plan(history))
            stop = self.planner.stop
            self.cycles += 1
            self.u_hold = u
            self.rows[-1][3] = u
            self.answered[stamp] = u
        if stop is not None and not was_stopped:
            self.log.info(f"task {self.task + 1}: blade stopped ({stop.reason} at t={stop.t:.1f} s)")
        self.publish_cmd(stamp, u)

    def publish_cmd(self, stamp: int, u_mmps: float) -> None:
        msg = self.TwistStamped()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        msg.header.frame_id = self.codec.task_frame_id(max(self.task, 0))
        msg.twist.linear.x = float(mmps_to_mps(u_mmps))
        self.pub_cmd.publish(msg)


def main(args: list[str] | None = None) -> int:
    """Console entry point ``peel_planner_node`` (``--ros-args --params-file ... -p ...``)."""
    from peel_msgs_py.runtime import rclpy
    from peel_msgs_py.runtime.entry import run_node

    return run_node(NODE_NAME, lambda argv: PlannerNode(), lambda node: rclpy.spin(node.node), args)


if __name__ == "__main__":
    sys.exit(main())

"""``peel_live``: the running graph on a Foxglove WebSocket server (``peel graph --live [PORT]``,
docs/graph.md "Live view").

    python -m peel_bringup.live_node [--port 8765] [--host 127.0.0.1] [--params FILE]

A thin rclpy adapter: it subscribes to the graph's topics (each with the profile its
publishers offer, :mod:`peel_msgs_py.topics`), turns every message into the JSON message of its
channel (:mod:`.live_schema`, ROS-free) and logs it on the Foxglove SDK's channel of that name,
which the SDK's server sends to every subscribed client (the Foxglove WebSocket protocol, which
foxglove-sdk 0.30.3 serves under the subprotocol names ``foxglove.sdk.v1`` and
``foxglove.sdk.v1.1``). The server binds to 127.0.0.1 unless ``--host`` says otherwise.
Stamped messages carry their ``header.stamp`` as log time; the others the node's ROS time
(simulated time under ``use_sim_time``, as every node of the graph), so a plot of the live view
runs on the graph's clock. A message that does not decode, or holds a non-finite number (JSON
has none), is dropped with a counted, rate-limited warning (:class:`~peel_msgs_py.wire.DropLog`).

``/peel/trajectory`` is decoded with :mod:`peel_msgs_py.codec` and J of Eq. 3 split into its
terms by the planner's own critics (:func:`peel_planner_node.cost.episode_cost_terms`, with the
planner's configuration and ``--params`` on top); torch is imported at the first finished task.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from typing import Any

import foxglove
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray, Int64, String

from peel_msgs_py import inbox, topics
from peel_msgs_py.cliargs import ArgumentParser, int_arg, run_main
from peel_msgs_py.errors import PeelError
from peel_msgs_py.params import load_node_params
from peel_msgs_py.ros.main import exit_now, run_node
from peel_msgs_py.wire import DropLog

from . import live_schema as S
from .graph import LIVE, LIVE_HOST, LIVE_PORT

NODE_NAME = LIVE
#: Foxglove's default WebSocket port (its "Open connection" dialog proposes it).
DEFAULT_PORT = LIVE_PORT
#: The only address the server binds to unless asked otherwise.
DEFAULT_HOST = LIVE_HOST

#: ROS-shaped stream topic -> (message type, conversion to its channel's message).
STREAMS: dict[str, tuple[type, Callable[[Any], S.Message]]] = {
    topics.WRENCH: (WrenchStamped, S.wrench_stamped),
    topics.TWIST: (TwistStamped, S.twist_stamped),
    topics.POSE: (PoseStamped, S.pose_stamped),
    topics.CMD_VEL: (TwistStamped, S.twist_stamped),
}


class LiveChannels:
    """One SDK channel per topic of :data:`.live_schema.CHANNELS`, JSON with its JSON schema."""

    def __init__(self) -> None:
        self.channels = {name: foxglove.Channel(name, schema=schema)
                         for name, schema in S.CHANNELS.items()}

    def log(self, topic: str, message: S.Message, time_ns: int) -> None:
        """Send ``message`` on ``topic`` at ``time_ns``; ValueError for a non-finite number."""
        data = json.dumps(message, allow_nan=False, separators=(",", ":")).encode()
        self.channels[topic].log(data, log_time=max(int(time_ns), 0))


def cost_terms(override: str | None) -> Callable[[Any], dict[str, Any]]:
    """J of Eq. 3 of a finished trajectory split into its terms, with the planner's cost
    parameters (``override`` on top); torch is imported at the first call."""
    cost: list[Any] = []

    def terms(traj: Any) -> dict[str, Any]:
        if not cost:
            from peel_planner_node.config import PlannerConfig
            from peel_planner_node.cost import Cost

            cfg = PlannerConfig.from_params(load_node_params("peel_planner_node", override))
            cost.append(Cost(cfg.cost))
        return cost[0].episode_terms(traj)

    return terms


class LiveNode(Node):
    """Subscribes to the graph's topics and logs each message on its live channel."""

    def __init__(self, out: LiveChannels, terms: Callable[[Any], dict[str, Any]]) -> None:
        super().__init__(NODE_NAME)
        self.out, self.terms, self.drops = out, terms, DropLog()
        self.tasks_seen = 0
        for name, (kind, convert) in STREAMS.items():
            self.listen(kind, name, lambda m, n=name, c=convert: self.send(n, c(m), S.stamp_ns(m)))
        self.listen(Int64, topics.MODEL_VERSION,
                    lambda m: self.send(topics.MODEL_VERSION, S.int64(m), self.now_ns()))
        self.listen(String, topics.MODEL_INFO, self.on_model_info)
        self.listen(String, topics.MODEL_UPDATE, self.on_model_update)
        self.listen(Float64MultiArray, topics.TRAJECTORY, self.on_trajectory)
        self.listen(DiagnosticArray, topics.DIAGNOSTICS, self.on_diagnostics)

    def listen(self, kind: type, name: str, callback: Callable[[Any], None]) -> None:
        self.create_subscription(kind, name, callback,
                                 topics.qos_profile(name, subscriber=True))

    def now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def drop(self, topic: str, name: str, why: str) -> None:
        line = self.drops.drop(topic, name, why)
        if line is not None:
            self.get_logger().warn(line)

    def send(self, topic: str, message: S.Message, time_ns: int) -> None:
        try:
            self.out.log(topic, message, time_ns)
        except ValueError:
            self.drop(topic, "a field", "holds a non-finite number (not sent)")

    def warn(self, line: str) -> None:
        self.get_logger().warn(line)

    def on_model_info(self, msg: String) -> None:
        rec = inbox.take(self.drops, topics.MODEL_INFO, inbox.model_record, msg, self.warn)
        if rec is None:
            return
        self.send(S.LIVE_MODEL, S.model_record(rec), self.now_ns())

    def on_model_update(self, msg: String) -> None:
        rep = inbox.take(self.drops, topics.MODEL_UPDATE, inbox.update_report, msg, self.warn)
        if rep is None:
            return
        self.send(S.LIVE_UPDATE, S.update_report(rep), self.now_ns())

    def on_trajectory(self, msg: Float64MultiArray) -> None:
        traj = inbox.take(self.drops, topics.TRAJECTORY, inbox.trajectory, msg, self.warn)
        if traj is None:
            return
        try:
            terms = self.terms(traj)
        except PeelError as exc:
            self.drop(topics.TRAJECTORY, "cost terms", f"cannot be computed: {exc}")
            return
        self.tasks_seen += 1
        task = int(traj.meta.get("task_index", self.tasks_seen - 1)) + 1
        self.send(S.LIVE_TASK, S.task_report(task, traj, terms), self.now_ns())

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        array, stamp = S.diagnostic_array(msg), S.stamp_ns(msg)
        self.send(topics.DIAGNOSTICS, array, stamp)
        for status in array["status"]:
            for topic, state in ((S.LIVE_PLANNER, S.planner_state(status)),
                                 (S.LIVE_LINK, S.link_state(status))):
                if state is not None:
                    self.send(topic, state, stamp)


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="peel_live", description=__doc__.split("\n\n")[0])
    p.add_argument("--port", type=int_arg(0, 65535), default=DEFAULT_PORT,
                   help="WebSocket port (default %(default)s; 0: one the system chooses)")
    p.add_argument("--host", default=DEFAULT_HOST,
                   help="address to bind (default %(default)s: this machine only)")
    p.add_argument("--params", metavar="FILE", default=None,
                   help="parameter override file (the planner's cost terms for J)")
    return p


def main(argv: list[str] | None = None) -> int:
    """Serve the live view until SIGINT / SIGTERM; returns the exit status."""
    from rclpy.utilities import remove_ros_args

    given = list(sys.argv[1:] if argv is None else argv)
    args = _parser().parse_args(remove_ros_args([NODE_NAME, *given])[1:])  # ros2 launch adds some
    try:
        server = foxglove.start_server(name="peel", host=args.host, port=args.port)
    except Exception as exc:  # the SDK raises its own error types for a port in use
        raise PeelError(f"cannot serve the live view on {args.host}:{args.port}: {exc}") from None
    print(f"{NODE_NAME}: serving the live view on ws://{args.host}:{server.port}", flush=True)
    out = LiveChannels()
    try:
        return run_node(NODE_NAME, lambda: LiveNode(out, cost_terms(args.params)),
                        [NODE_NAME, "--ros-args", "-p", "use_sim_time:=true"])
    finally:
        server.stop()


if __name__ == "__main__":
    exit_now(run_main(NODE_NAME, main))
